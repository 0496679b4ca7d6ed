"""One whole station of tests/test_db_outage_pg.py in its own process: simulated boards, the real
Station with its writer and journal on the line's PostgreSQL (through the test's proxy), and its
web API on PORT. Prints READY once it serves; each line on stdin starts a batch of fast-thermal on
every slot (the station's answer, or its refusal, is printed as one JSON line); EOF ends it: it
waits for the batch, closes like a SIGTERM would and prints the summary JSON line.

    python tests/outage_station_child.py URL NAME SEED N_SERIAL SPEED PORT JOURNAL PREFIX
"""

from __future__ import annotations

import asyncio
import json
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.sim.physics import draw_population  # noqa: E402
from drivers.sim.station_sim import SimStation  # noqa: E402
from cli.commands.demo import sim_config  # noqa: E402
from station.config import parse_config  # noqa: E402
from station.daemon.heap import freeze_startup_heap  # noqa: E402
from station.daemon.storage import open_database  # noqa: E402
from station.daemon.supervisor import Station  # noqa: E402
from web.server import serve_web, stop_web  # noqa: E402

PROFILE = "fast-thermal"


async def main(url: str, name: str, seed: int, n_serial: int, speed: float, port: int, journal: str,
               prefix: str) -> None:
    truths = draw_population(n_serial, seed, serial_prefix=prefix)
    async with SimStation(n_serial=n_serial, n_can=0, seed=seed, speed=speed, truths=truths) as sim:
        raw = sim_config(sim, speed=speed, db_url=url)
        raw["name"] = name
        raw["journal_path"] = journal
        raw["tokens"] = [{"name": "mes", "token": "mes-token-0123456789", "role": "mes"},
                         {"name": "line", "token": "line-token-0123456789", "role": "operator"}]
        cfg = parse_config(raw, f"<{name}>")
        db = open_database(cfg.database_url, station=cfg.name, journal_path=cfg.journal_path)
        station = Station(cfg, db=db)
        await station.start()
        server, task = await serve_web(station, "127.0.0.1", port)
        freeze_startup_heap()  # as station serve does after its web server started
        print("READY", flush=True)
        loop = asyncio.get_running_loop()
        batches: list[int] = []
        # each batch's status is taken when it ends: the daemon holds only its last ended batch
        ended: dict[int, asyncio.Task] = {}
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line:
                break
            try:
                batches.append(station.start_batch(PROFILE, None, name))
                ended[batches[-1]] = asyncio.create_task(station.wait_batch(batches[-1], timeout_s=600))
                print(json.dumps({"started": batches[-1]}), flush=True)
            except Exception as exc:  # noqa: BLE001 - the test reads the refusal
                print(json.dumps({"refused": f"{type(exc).__name__}: {exc}"}), flush=True)
        out = {"station": name, "batches": []}
        for bid in batches:
            status = await ended[bid]
            out["batches"].append({
                "batch_id": bid, "state": status["state"], "error": status["error"],
                "slots": [{"slot": s["slot"], "serial": s["serial"], "state": s["state"], "run_id": s.get("run_id"),
                           "samples": s.get("samples"), "segments": s.get("segments"),
                           "verdict": (s.get("decision") or {}).get("verdict")}
                          for s in status["slots"]]})
        out["writer"] = {k: station.writer.stats[k] for k in ("dropped_events", "storage_failures", "journaled_events",
                                                              "forwarded_events", "abandoned_events")}
        await station.close("test done")
        await stop_web(server, task)
        db.dispose()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    a = sys.argv[1:]
    asyncio.run(main(a[0], a[1], int(a[2]), int(a[3]), float(a[4]), int(a[5]), a[6], a[7]))
