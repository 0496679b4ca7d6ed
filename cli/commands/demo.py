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
import sys
import time
from pathlib import Path

from cli.report import results_table
from cli.runtime import install_stop_signals, setup_logging
from contracts.types import StationError
from web.server import serve_web, stop_web


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
    p.add_argument("--mes-hold", action="append", default=None, metavar="SERIAL",
                   help="a serial the demo's MES stand-in holds (its route check refuses it; design 5.4); "
                        "repeatable; default: the third board's serial (with 3 boards or more); 'none' holds none")
    p.add_argument("--no-mes", action="store_true", help="no MES stand-in and no route check")
    p.add_argument("--mes-policy", choices=("refuse", "proceed_and_flag"), default="refuse",
                   help="what the station does when the MES does not answer ([mes.route_check] when_unanswered)")
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
               timing: dict | None = None, profiles: dict | None = None, route_check: dict | None = None) -> dict:
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
    if route_check:
        cfg["mes"] = {"route_check": route_check}
    return cfg


DEMO_HOLD_REASON = "on quality hold: NCR-2291 (voids under U3 at X-ray)"


def demo_holds(args: argparse.Namespace, serials: list[str]) -> dict[str, str]:
    """The serials the demo's MES stand-in holds: --mes-hold, or the third board's (the flow is
    visible on the page: that slot stops before the lamp heats, with the MES's reason)."""
    if args.mes_hold is None:  # a demo of one or two boards keeps them all (nothing else would run)
        return {serials[2]: DEMO_HOLD_REASON} if len(serials) >= 3 else {}
    return {s: DEMO_HOLD_REASON for s in args.mes_hold if s.lower() != "none"}


def truth_by_slot(sim) -> dict[str, object]:
    out = {}
    for i in range(sim.n_serial):
        out[f"s{i + 1:02d}"] = sim.truths[i]
    for j in range(sim.n_can):
        out[f"c{j + 1:02d}"] = sim.truths[sim.n_serial + j]
    return out


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
    from station.daemon.heap import freeze_startup_heap
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
        mes = None
        if not args.no_mes:  # the line's MES, answering the route check (drivers/sim/mes_standin.py)
            from drivers.sim.mes_standin import MesStandIn

            mes = MesStandIn(demo_holds(args, [t.serial for t in sim.truths])).start()
            for serial, why in mes.holds.items():
                print(f"station demo: the MES stand-in holds {serial}: {why}", flush=True)
        cfg = parse_config(sim_config(sim, speed=args.speed, db_url=db_url, fixture=not args.no_fixture,
                                      http_host=args.host, http_port=args.port,
                                      route_check=None if mes is None else
                                      {"url": mes.url, "when_unanswered": args.mes_policy}), "<demo>")
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
                freeze_startup_heap()  # full GC passes walk only what runs make, not the imports (150-200 ms each)
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
            if mes is not None:
                mes.stop()
            if hasattr(db, "dispose"):
                db.dispose()
        return rc
