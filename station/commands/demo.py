"""`station demo`: a whole simulated station on this machine, with the real daemon driving it.

SimStation puts N serial boards on pseudo-terminals, M CAN boards behind an slcan adapter on a
pseudo-terminal, and the lamp relay, fixture and plate thermometer on a Modbus TCP server on
127.0.0.1, all in compressed time (--speed). The daemon connects to them through the very drivers
`station serve` uses, stores into SQLite, serves the operator page and starts a fast-thermal batch.
--once runs one batch headless and prints a results table (simulated truth beside each result).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from pathlib import Path

from contracts.types import AXES, StationError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--speed", type=float, default=60.0, help="simulated seconds per wall second (default 60)")
    p.add_argument("--serial", type=int, default=8, help="simulated serial boards (default 8)")
    p.add_argument("--can", type=int, default=4, help="simulated CAN boards (default 4)")
    p.add_argument("--seed", type=int, default=1, help="population seed")
    p.add_argument("--boards", action="append", default=[], metavar="KIND[:N]",
                   help="boards running the C reference firmware (firmware/) in the next N slots (default 2): "
                        "firmware-host (one Linux process per board), firmware-qemu (Cortex-M4 in qemu-system-arm), "
                        "firmware-host-can (CAN nodes), python (the Python board model, the default); repeatable")
    p.add_argument("--effect", action="append", default=[], metavar="NAME", help="hidden physics effect to switch on")
    p.add_argument("--profile", default="fast-thermal", help="profile of the automatic batch")
    p.add_argument("--no-batch", action="store_true", help="do not start a batch automatically")
    p.add_argument("--once", action="store_true", help="run one batch headless, print the results and exit")
    p.add_argument("--no-fixture", action="store_true", help="no motorized fixture: a person is prompted to turn "
                   "the plate (see --operator)")
    p.add_argument("--operator", choices=("person", "page"), default="person",
                   help="with --no-fixture: 'person' (default) a simulated person turns the plate and presses Done "
                        "with human timing (seconds to minutes of sample time, sometimes Done first); 'page': the "
                        "plate turns only when somebody presses Done on the page")
    p.add_argument("--operator-seed", type=int, default=None, metavar="N",
                   help="seed of the simulated person's timing (default: --seed)")
    p.add_argument("--host", default="127.0.0.1", help="HTTP host (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080)")
    p.add_argument("--no-web", action="store_true", help="do not serve the web page")
    p.add_argument("--db", default=None, help="database URL (default sqlite:///./var/demo.db)")
    p.add_argument("--new-database", action="store_true",
                   help="begin a new database where the marker says one with batches was (deleted or replaced)")
    p.add_argument("--json", dest="json_out", default=None, metavar="FILE", help="with --once: write the results as JSON")
    p.add_argument("--verbose", "-v", action="store_true")


# Sign-in tokens of the demo station (printed at start and in the README's quick start).
DEMO_TOKENS: tuple[dict, ...] = (
    {"token": "demo-operator-token", "role": "operator", "name": "demo"},
    {"token": "demo-admin-token", "role": "admin", "name": "demo"},
    {"token": "demo-mes-token", "role": "mes", "name": "demo"},
)


def sim_config(sim, *, speed: float, db_url: str, fixture: bool = True, thermometer: bool = True,
               chamber: bool = True,
               http_host: str = "127.0.0.1", http_port: int = 8080, limits: dict | None = None,
               timing: dict | None = None, profiles: dict | None = None) -> dict:
    """A station config (as the TOML would give it) pointing at a running SimStation's links."""
    slots: list[dict] = [{"name": f"s{i + 1:02d}", "serial": port} for i, port in enumerate(sim.serial_ports)]
    for j, node in enumerate(sim.can_node_ids):
        slots.append({"name": f"c{j + 1:02d}", "can": {"interface": "slcan", "channel": sim.can_channel, "node": node}})
    tcp = {"host": sim.modbus_host, "port": sim.modbus_port}
    cfg: dict = {
        "name": "demo station (simulated)",
        "database_url": db_url,
        "http": {"host": http_host, "port": http_port},
        "limits": {"max_dut_temp_c": 85.0, "max_plate_temp_c": 90.0, "lamp_max_on_s": 4800.0, **(limits or {})},
        "timing": {"speed": speed, "stall_timeout_s": 10.0, **(timing or {})},
        "slots": slots,
        "lamp": {"tcp": tcp, "unit": 1},
        "tokens": [dict(t) for t in DEMO_TOKENS],
    }
    if fixture:
        cfg["fixture"] = {"tcp": tcp, "unit": 3}
    if thermometer:
        cfg["thermometer"] = {"tcp": tcp, "unit": 2}
    if chamber:  # every instrument of design 3.3 is simulated, so every built-in profile runs
        cfg["chamber"] = {"tcp": tcp, "unit": 4}
    if profiles:
        cfg["profiles"] = profiles
    return cfg


def truth_by_slot(sim) -> dict[str, object]:
    out = {}
    for i in range(sim.n_serial):
        out[f"s{i + 1:02d}"] = sim.truths[i]
    for j in range(sim.n_can):
        out[f"c{j + 1:02d}"] = sim.truths[sim.n_serial + j]
    return out


def results_table(status: dict, truths: dict | None = None) -> tuple[str, dict]:
    """Text table of a batch's per-DUT results (and errors vs truth); also the numbers as a dict."""
    lines = []
    head = f"{'slot':5} {'serial':14} {'state':9} " + " ".join(f"TDB{a}" .rjust(8) for a in AXES) + " " + \
        " ".join(f"TDSF{a}".rjust(8) for a in AXES)
    if truths:
        head += "  max|dTDB| max|dTDSF|"
    lines.append(head)
    summary: dict = {"batch": status["id"], "state": status["state"], "error": status["error"], "duts": {}}
    for s in status["slots"]:
        res = s.get("result") or {}
        axes = res.get("axes") or {}
        row = f"{s['slot']:5} {str(s['serial'] or '-'):14} {s['state']:9} "
        entry: dict = {"serial": s["serial"], "state": s["state"], "fault_reason": s["fault_reason"]}
        if axes:
            tdb = [axes[a]["tdb_mg_per_c"] for a in AXES]
            tdsf = [axes[a]["tdsf_ppm_per_c"] for a in AXES]
            row += " ".join(f"{v:8.4f}" for v in tdb) + " " + " ".join(f"{v:8.1f}" for v in tdsf)
            entry.update(tdb_mg_per_c=tdb, tdsf_ppm_per_c=tdsf)
            t = truths.get(s["slot"]) if truths else None
            if t is not None:
                e_tdb = max(abs(a - b) for a, b in zip(tdb, list(t.tdb_mg_per_c)))
                e_tdsf = max(abs(a - b) for a, b in zip(tdsf, list(t.tdsf_ppm_per_c)))
                row += f"  {e_tdb:9.4f} {e_tdsf:9.1f}"
                entry.update(err_tdb_mg_per_c=e_tdb, err_tdsf_ppm_per_c=e_tdsf,
                             true_tdb_mg_per_c=[float(x) for x in t.tdb_mg_per_c],
                             true_tdsf_ppm_per_c=[float(x) for x in t.tdsf_ppm_per_c])
        elif res.get("steps"):  # SFEM (sfem-24, contracts/sfem_result.py): the residual before -> after per step
            temps = res["steps"]
            row += "SFEM " + "  ".join(
                f"{t['temp_c']:.0f} C: {t['rmse_before_mg']:.1f} -> {t['rmse_after_mg']:.2f} mg" for t in temps)
            entry["sfem"] = [{"temp_c": t["temp_c"], "rmse_before_mg": t["rmse_before_mg"],
                              "rmse_after_mg": t["rmse_after_mg"], "rmse_heldout_mg": t.get("rmse_heldout_mg")}
                             for t in temps]
        elif s["fault_reason"]:
            row += s["fault_reason"]
        v = s.get("decision")
        if v:  # the station's decision (station/decisions/verdicts.py)
            row += f"  {v['verdict'].upper()} {v.get('grade') or ''} ({v.get('reason') or ''})"
            entry.update(verdict=v["verdict"], grade=v.get("grade"), tray=v.get("tray"), reason=v.get("reason"),
                         attempt=v.get("attempt"))
        lines.append(row)
        pv = program_verify_summary(s.get("program"), s.get("verification"))
        if pv is not None:
            entry["program_verify"] = pv
            lines.append(" " * 6 + program_verify_line(pv))
        summary["duts"][s["slot"]] = entry
    return "\n".join(lines), summary


def program_verify_summary(program: dict | None, verification: dict | None) -> dict | None:
    """Program and verify of one DUT as the demo reports it (None: the profile has no program step)."""
    if not program:
        return None
    ver = verification or {}
    return {
        "programmed": bool(program.get("programmed")),
        "crc": program.get("crc"),
        "readback_crc": program.get("readback_crc"),
        "crc_match": bool(program.get("readback_identical")),
        "comp_on": bool(program.get("comp")),
        "attempts": program.get("attempts"),
        "error_kind": program.get("error_kind"),
        "error": program.get("error"),
        "written_tdb_mg_per_c": program.get("tdb_mg_per_c"),
        "written_tdsf_ppm_per_c": program.get("tdsf_ppm_per_c"),
        "verified": ver.get("passed") if verification else None,
        "e_before_mg": ver.get("e_before_mg"),
        "e_after_mg": ver.get("e_after_mg"),
        "flags": list(ver.get("flags") or []),
    }


def program_verify_line(pv: dict) -> str:
    """One table line: what was written and proven, and the verified drift error per axis."""
    if not pv["programmed"]:
        return f"program: NOT programmed ({pv.get('error_kind') or '-'}: {pv.get('error') or '-'})"
    text = (f"program: CRC {pv['crc']} {'= read back' if pv['crc_match'] else '!= read back ' + str(pv['readback_crc'])}"
            f", compensation {'on' if pv['comp_on'] else 'OFF'}, {pv['attempts']} attempt(s)")
    after, before = pv.get("e_after_mg") or {}, pv.get("e_before_mg") or {}
    if pv["verified"] is None:
        return text + "; not verified"
    per_axis = " ".join(f"{a} {_mg(after.get(a))} (was {_mg(before.get(a))})" for a in AXES)
    return text + f"; verified E after [mg]: {per_axis}: {'PASS' if pv['verified'] else 'FAIL'}"


def _mg(v) -> str:
    return "-" if v is None else f"{float(v):.2f}"


async def serve_web(station, host: str, port: int, *, header_timeout_s: float | None = None,
                    keep_alive_s: float | None = None, max_connections: int | None = None):
    """The web app in this event loop (same loop as the daemon: the facade is not thread-safe).

    A web app that cannot be imported is a hard error (one line, non-zero exit), never a warning:
    a daemon without its page looks alive to an operator who cannot reach it.
    header_timeout_s / keep_alive_s / max_connections: default from the station's config [http].
    """
    try:
        from web.app import create_app
    except ImportError as exc:
        raise StationError(f"the operator page cannot be served: {exc} "
                           "(the installation is incomplete: run `pip install .` or ./scripts/setup.sh)") from exc
    import contextlib

    import uvicorn

    class _Server(uvicorn.Server):
        @contextlib.contextmanager
        def capture_signals(self):  # the daemon owns SIGINT/SIGTERM (lamp off first)
            yield

    from web.http_guard import ACCEPT_BATCH, HttpGuard, install_accept_error_filter

    http_cfg = getattr(getattr(station, "config", None), "http", None)
    header_timeout_s = getattr(http_cfg, "header_timeout_s", 10.0) if header_timeout_s is None else header_timeout_s
    keep_alive_s = getattr(http_cfg, "keep_alive_s", 5) if keep_alive_s is None else keep_alive_s
    max_connections = getattr(http_cfg, "max_connections", 512) if max_connections is None else max_connections
    install_accept_error_filter()  # a full file table: one line per 10 s, not a traceback per accept()
    sock = _listen_socket(host, port)  # our own bind: a taken port is one clear line, not uvicorn's exit(3)
    app = create_app(station)
    guard = HttpGuard(header_timeout_s=header_timeout_s, max_connections=max_connections, accept_batch=ACCEPT_BATCH)
    # Slow clients (issue 37, web/http_guard.py): a request head within header_timeout_s, idle
    # keep-alive closed after keep_alive_s, at most max_connections open (the oldest waiting for a
    # head is evicted), and at most ACCEPT_BATCH sockets accepted per loop tick (the listen backlog).
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", lifespan="on",
                            http=guard.protocol_class(), timeout_keep_alive=keep_alive_s, backlog=ACCEPT_BATCH)
    server = _Server(config)
    task = asyncio.get_running_loop().create_task(server.serve(sockets=[sock]), name="http")
    for _ in range(200):
        if server.started or task.done():
            break
        await asyncio.sleep(0.02)
    if task.done():
        exc = task.exception() if not task.cancelled() else None
        raise StationError(f"cannot serve HTTP on {host}:{port}: {exc or 'server exited'}")
    from station.daemon.heap import freeze_startup_heap

    freeze_startup_heap()  # full GC passes walk only what runs make, not the imports (150-200 ms each)
    server.http_guard = guard  # its counters, for tests and diagnostics
    return server, task


def _listen_socket(host: str, port: int):
    import socket

    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(family, kind, proto)
    except (OSError, UnicodeError) as exc:
        raise StationError(f"cannot serve HTTP on {host}:{port}: {exc}") from None
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        raise StationError(f"cannot serve HTTP on {host}:{port}: {exc.strerror or exc} (is another station "
                           "or program using this port? choose another with --port)") from None
    sock.setblocking(False)
    return sock


async def stop_web(server, task) -> None:
    if server is None:
        return
    server.should_exit = True
    try:
        await asyncio.wait_for(task, 5.0)
    except (asyncio.TimeoutError, Exception):
        task.cancel()


def install_stop_signals(stop: asyncio.Event) -> None:
    import signal

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):
            pass


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not verbose:  # errors reach the user as one StationError line, not library chatter
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose)
    if args.serial < 0 or args.can < 0 or args.serial + args.can == 0:
        raise StationError("need at least one simulated board (--serial/--can)")
    if args.can > 127:
        raise StationError("--can: at most 127 CAN boards on one bus")
    if args.speed <= 0:
        raise StationError("--speed must be > 0")
    if args.once and args.no_fixture and args.operator == "page":
        raise StationError("--once --no-fixture needs --operator person: nobody is at the page to press Done")
    if not args.no_batch or args.once:  # the demo's config has the built-in profiles only
        from station.profiles import check_profile_name

        check_profile_name(args.profile)
    return asyncio.run(_main(args))


async def _main(args: argparse.Namespace) -> int:
    from drivers.sim.station_sim import SimStation
    from station.config import parse_config
    from station.daemon.storage import open_database
    from station.daemon.supervisor import Station

    db_url = args.db or f"sqlite:///{Path('var').resolve() / 'demo.db'}"
    stop = asyncio.Event()
    install_stop_signals(stop)
    from drivers.sim.firmware_boards import plan_firmware

    try:
        firmware = plan_firmware(args.boards, args.serial, args.can)
    except ValueError as exc:
        print(f"station demo: --boards: {exc}", file=sys.stderr)
        return 2
    async with SimStation(n_serial=args.serial, n_can=args.can, seed=args.seed, speed=args.speed,
                          effects=tuple(args.effect), firmware=firmware) as sim:
        cfg = parse_config(sim_config(sim, speed=args.speed, db_url=db_url, fixture=not args.no_fixture,
                                      http_host=args.host, http_port=args.port), "<demo>")
        db = open_database(cfg.database_url, station=cfg.name, allow_new=args.new_database,
                           journal_path=cfg.journal_path)
        interrupted = db.mark_interrupted("station restarted") if hasattr(db, "mark_interrupted") else []
        from station.decisions.limits_audit import record_limit_changes

        record_limit_changes(db, cfg)  # a limit set edited in the config since the last start: audited
        station = Station(cfg, db=db)
        server = task = None
        rc = 0
        hands = None
        if args.no_fixture:  # without a fixture somebody turns the plate (drivers/sim/operator.py)
            from drivers.sim.operator import Person, operator_hands

            if args.operator == "person":
                person = Person(sim.world, lambda b, pid: station.answer_prompt(b, pid, "done", by="simulated person"),
                                seed=args.seed if args.operator_seed is None else args.operator_seed)
                hands = asyncio.get_running_loop().create_task(person.run(station.bus))
            else:
                hands = asyncio.get_running_loop().create_task(operator_hands(station.bus, sim.world))
        try:
            await station.start()
            station.judge_interrupted(interrupted)  # a killed daemon's runs ended then: error verdicts
            faulted = [s for s in station.slots_status() if s["state"] == "faulted"]
            for s in faulted:
                print(f"station demo: slot {s['slot']}: {s['fault_reason']}", file=sys.stderr)
            if not args.once and not args.no_web:
                server, task = await serve_web(station, args.host, args.port)
                if server is not None:
                    print(f"station demo: operator page on http://{args.host}:{args.port}/ "
                          f"({args.serial} serial + {args.can} CAN boards, speed x{args.speed:g}, db {db_url})",
                          flush=True)
                    print("station demo: sign in with one of these tokens: "
                          + ", ".join(f"{t['role']}: {t['token']}" for t in DEMO_TOKENS), flush=True)
            batch_id = None
            if not args.no_batch or args.once:
                batch_id = station.start_batch(args.profile, None, "demo", by="station demo")
                print(f"station demo: batch {batch_id} ({args.profile}) started", flush=True)
            if args.once:
                assert batch_id is not None
                t0 = time.monotonic()
                done = asyncio.create_task(station.wait_batch(batch_id))
                stopper = asyncio.create_task(stop.wait())
                await asyncio.wait({done, stopper}, return_when=asyncio.FIRST_COMPLETED)
                stopper.cancel()
                if not done.done():
                    done.cancel()
                    print("station demo: interrupted", file=sys.stderr)
                    rc = 130
                else:
                    await station.flush_db()
                    status = station.batch_status(batch_id)
                    table, summary = results_table(status, truth_by_slot(sim))
                    summary["wall_s"] = time.monotonic() - t0
                    summary["sample_time_s"] = status["sample_time_s"]
                    print(f"batch {batch_id} {status['state']} {status['error']} in {summary['wall_s']:.1f} s wall, "
                          f"{status['sample_time_s']:.0f} s sample time")
                    print(table, flush=True)
                    if status.get("note"):  # e.g. a validation batch: no calibration result is expected
                        print(status["note"], flush=True)
                    dec = status.get("decision") or {}
                    if dec.get("judged"):
                        print("verdicts: " + ", ".join(f"{k} {n}" for k, n in dec["verdicts"].items())
                              + " | grades: " + ", ".join(f"{k} {n}" for k, n in sorted(dec["grades"].items())), flush=True)
                        summary["decision"] = dec
                    if args.json_out:
                        import json

                        Path(args.json_out).write_text(json.dumps(summary, indent=2))
                    rc = 0 if status["state"] == "finished" else 1
            else:
                await stop.wait()
        finally:
            if hands is not None:  # (not `task`: that name is the web server's)
                hands.cancel()
            await station.close("daemon shutdown")  # lamp off first, then the web server
            await stop_web(server, task)
            if hasattr(db, "dispose"):
                db.dispose()
        return rc
