"""One WHOLE station daemon of tests/test_two_daemons_pg.py, in its own process: simulated boards
(SimStation: ptys and the Modbus devices) whose serials are chosen by the test (the same new serials
in both daemons, each daemon its own physics), the real Station supervisor with its DbWriter on the
shared PostgreSQL database, no web. Prints READY once started, starts its batch when the test
writes a line on stdin (both daemons at the same moment), prints one JSON line when it ends.

Race alignment (test instrumentation, no change of behaviour): the daemon's k-th create_run waits
(at most 3 s) until the other daemon reached its k-th create_run too, files in RENDEZVOUS_DIR, so
both daemons meet each new serial in the same millisecond: the race the old select-then-insert lost.

    python tests/two_daemon_child.py URL NAME SEED N_SERIAL SPEED PREFIX RENDEZVOUS_DIR
"""

from __future__ import annotations

import asyncio
import json
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.sim.physics import draw_population  # noqa: E402
from drivers.sim.station_sim import SimStation  # noqa: E402
from cli.commands.demo import sim_config  # noqa: E402
from station.config import parse_config  # noqa: E402
from station.daemon.storage import open_database  # noqa: E402
from station.daemon.supervisor import Station

PROFILE = "fast-thermal"
PEERS = 2
RENDEZVOUS_TIMEOUT_S = 3.0


def align_create_run(db, name: str, rendezvous: Path) -> None:
    """Wrap db.create_run: call k waits for the peer's call k (files k.NAME), then runs."""
    real = db.create_run
    calls = {"k": 0}

    def create_run(*args, **kwargs):
        k = calls["k"]
        calls["k"] += 1
        (rendezvous / f"{k}.{name}").touch()
        deadline = time.monotonic() + RENDEZVOUS_TIMEOUT_S
        while len(list(rendezvous.glob(f"{k}.*"))) < PEERS and time.monotonic() < deadline:
            time.sleep(0.0005)
        return real(*args, **kwargs)

    db.create_run = create_run


async def main(url: str, name: str, seed: int, n_serial: int, speed: float, prefix: str, rendezvous: Path) -> None:
    truths = draw_population(n_serial, seed, serial_prefix=prefix)  # same serials, this daemon's physics
    async with SimStation(n_serial=n_serial, n_can=0, seed=seed, speed=speed, truths=truths) as sim:
        raw = sim_config(sim, speed=speed, db_url=url)
        raw["name"] = name
        cfg = parse_config(raw, f"<{name}>")
        db = open_database(cfg.database_url, station=cfg.name)
        align_create_run(db, name, rendezvous)
        station = Station(cfg, db=db)
        await station.start()
        print("READY", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
        t0 = time.monotonic()
        batch_id = station.start_batch(PROFILE, None, name)
        await station.wait_batch(batch_id, timeout_s=240)
        await station.flush_db()
        status = station.batch_status(batch_id)
        out = {
            "station": name, "batch_id": batch_id, "state": status["state"], "error": status["error"],
            "wall_s": round(time.monotonic() - t0, 1), "collision_retries": db.collision_retries,
            "writer": {k: station.writer.stats[k] for k in ("dropped_events", "storage_failures", "commits")},
            "slots": [{k: s.get(k) for k in ("slot", "serial", "state", "fault_reason", "run_id")} for s in status["slots"]],
        }
        await station.close("test done")
        db.dispose()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    a = sys.argv[1:]
    asyncio.run(main(a[0], a[1], int(a[2]), int(a[3]), float(a[4]), a[5], Path(a[6])))
