"""`station serve --config FILE`: the station daemon on real hardware as configured.

Connects the Modbus instruments (an unreachable lamp relay, fixture, thermometer or chamber is a
one-line error and exit 2), identifies every slot (a wrong port or a silent board faults only that
slot and is reported on stderr), serves the REST API / operator page and runs batches. SIGINT and
SIGTERM switch the lamp off before anything else, interrupt a running batch and exit.

Before anything touches the database or the hardware, serve (and serve --check) claims every
resource the config names (station/daemon/ownership.py): a station that is already running on them
keeps them, and this process stops in one line naming its PID and host, having written nothing.
"""

from __future__ import annotations

import argparse
import logging
import asyncio
import sys

from cli.report import results_table
from cli.runtime import install_stop_signals, setup_logging
from contracts.types import StationError
from web.server import serve_web, stop_web


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="station.toml", help="station config (TOML), default ./station.toml")
    p.add_argument("--host", default=None, help="override [http] host")
    p.add_argument("--port", type=int, default=None, help="override [http] port")
    p.add_argument("--no-web", action="store_true", help="no REST API / page (headless)")
    p.add_argument("--start-batch", metavar="PROFILE", default=None, help="start a batch of PROFILE at once")
    p.add_argument("--slots", default=None, help="with --start-batch: comma separated slot names (default all)")
    p.add_argument("--once", action="store_true", help="with --start-batch: exit when the batch ends (0 = finished)")
    p.add_argument("--resume", default=None, metavar="BATCH",
                   help="resume an interrupted batch (an id, or 'latest') at the step after its last completed one")
    p.add_argument("--check", action="store_true", help="check the config and the links, then exit")
    p.add_argument("--new-database", action="store_true",
                   help="begin a new database where the marker beside the SQLite file says one with batches was "
                        "(it was deleted or replaced): only when that database is really gone")
    p.add_argument("--verbose", "-v", action="store_true")


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose)
    if args.check and not args.verbose:
        # --check prints each faulted slot itself, one line each; no second copy from the log.
        logging.getLogger("station.daemon.slots").setLevel(logging.ERROR)
    from station.config import load_config

    cfg = load_config(args.config)
    if args.once and not (args.start_batch or args.resume):
        raise StationError("--once needs --start-batch PROFILE or --resume BATCH")
    if args.start_batch and args.resume:
        raise StationError("--start-batch and --resume exclude each other")
    if args.start_batch:
        from station.profiles import check_profile_name

        check_profile_name(args.start_batch, cfg)
    return asyncio.run(_main(args, cfg))


async def _main(args: argparse.Namespace, cfg) -> int:
    from station.daemon.ownership import StationClaim

    # First: the database, ports, relay and config this station owns. A running station keeps them
    # (--check included: no database write, no Modbus write, no port opened).
    claim = StationClaim.take(cfg, database_url=cfg.database_url, config_path=args.config,
                              command="station serve --check" if args.check else "station serve")
    try:
        return await _serve(args, cfg, claim)
    finally:
        claim.release()


async def _serve(args: argparse.Namespace, cfg, claim) -> int:
    from station.daemon.heap import freeze_startup_heap
    from station.daemon.storage import open_database
    from station.daemon.supervisor import Station

    stop = asyncio.Event()
    install_stop_signals(stop)
    try:
        db = open_database(cfg.database_url, station=cfg.name, allow_new=args.new_database,
                           journal_path=cfg.journal_path, forward=not args.check)
    except StationError:
        raise
    except Exception as exc:  # SQLAlchemy: bad URL, unwritable file, server down
        raise StationError(f"database {cfg.database_url}: {exc}") from None
    interrupted = db.mark_interrupted("station restarted") if hasattr(db, "mark_interrupted") else []
    from station.decisions.limits_audit import record_limit_changes

    record_limit_changes(db, cfg)  # a limit set edited in the config since the last start: audited
    station = Station(cfg, db=db, claim=claim)
    server = task = None
    rc = 0
    try:
        await station.start()
        station.judge_interrupted(interrupted)  # a killed daemon's runs ended then: error verdicts
        slots = station.slots_status()
        for s in slots:
            if s["state"] == "faulted":
                print(f"station serve: slot {s['slot']}: {s['fault_reason']}", file=sys.stderr, flush=True)
        ok = [s for s in slots if s["state"] != "faulted"]
        print(f"station serve: {len(ok)}/{len(slots)} slot(s) identified", flush=True)
        if args.check:
            return 0 if len(ok) == len(slots) else 1
        if not args.no_web:
            host = args.host or cfg.http.host
            port = args.port if args.port is not None else cfg.http.port
            server, task = await serve_web(station, host, port)
            freeze_startup_heap()  # full GC passes walk only what runs make, not the imports (150-200 ms each)
            if server is not None:
                print(f"station serve: listening on http://{host}:{port}/", flush=True)
        batch_id = None
        if args.start_batch:
            names = [s.strip() for s in args.slots.split(",")] if args.slots else None
            try:
                batch_id = station.start_batch(args.start_batch, names, "serve --start-batch", by="station serve")
            except ValueError as exc:
                raise StationError(str(exc)) from None
            print(f"station serve: batch {batch_id} ({args.start_batch}) started", flush=True)
        if args.resume:
            batch_id = _resume(station, db, args.resume)
            print(f"station serve: batch {batch_id} resumed", flush=True)
        if args.once and batch_id is not None:
            done = asyncio.create_task(station.wait_batch(batch_id))
            stopper = asyncio.create_task(stop.wait())
            await asyncio.wait({done, stopper}, return_when=asyncio.FIRST_COMPLETED)
            stopper.cancel()
            if done.done():
                await station.flush_db()
                status = station.batch_status(batch_id)
                print(f"batch {batch_id} {status['state']} {status['error']}")
                print(results_table(status)[0], flush=True)
                if status.get("note"):  # e.g. a validation batch: no calibration result is expected
                    print(status["note"], flush=True)
                rc = 0 if status["state"] == "finished" else 1
            else:
                done.cancel()
                rc = 130
        else:
            await stop.wait()
            rc = 0
    finally:
        await station.close("daemon shutdown")  # lamp off first, then the web server
        await stop_web(server, task)
        if hasattr(db, "dispose"):
            db.dispose()
    return rc


def _resume(station, db, which: str) -> int:
    """--resume BATCH|latest: one clear line when there is nothing (or nothing valid) to resume."""
    if which == "latest":
        ids = db.interrupted_batches() if hasattr(db, "interrupted_batches") else []
        if not ids:
            raise StationError("--resume latest: no interrupted batch in the database")
        batch_id = ids[-1]
    else:
        try:
            batch_id = int(which)
        except ValueError:
            raise StationError(f"--resume: {which!r} is neither a batch id nor 'latest'") from None
    try:
        return station.resume_batch(batch_id, "serve --resume")
    except KeyError:
        raise StationError(f"--resume: no batch {batch_id} in the database") from None
    except ValueError as exc:
        raise StationError(f"--resume: {exc}") from None
