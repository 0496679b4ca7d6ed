"""One 'station' of tests/test_multi_station.py, in its own process: its own Database (station
name) and DbWriter, writing results into the shared PostgreSQL database as fast as a real writer
commits them (small random pauses, 10 ms writer interval), then printing its writer's stats.

    python tests/multi_station_child.py URL STATION N_BATCHES RUNS_PER_BATCH SEED
"""

from __future__ import annotations

import json
import random
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from db import Database, DbWriter  # noqa: E402
from db_helpers import THERMAL_JSON  # noqa: E402
from contracts.events import DutResult, DutVerdict, SlotStateChanged  # noqa: E402
from contracts.run_records import ThermalReport


def main() -> None:
    url, station, n_batches, per_batch, seed = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
    rng = random.Random(seed)
    db = Database(url, station=station)
    writer = DbWriter(db, interval_s=0.01)
    runs = []
    for b in range(n_batches):
        batch = db.create_batch("fast-thermal", f"op-{station}", {"name": station})
        for i in range(per_batch):
            slot = f"s{i + 1:02d}"
            serial = f"{station}-{b:02d}-{i:02d}"
            run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial})
            writer.bind_run(batch, slot, run)
            runs.append((batch, slot, serial))
    for batch, slot, serial in runs:
        verdict = {"verdict": rng.choice(["pass", "pass", "marginal", "fail"]), "grade": "A", "tray": "T1",
                   "attempt": 1, "limits_name": "LIS3DSH", "limits_version": "1"}
        writer.submit(DutResult(batch, slot, serial, thermal=ThermalReport.from_json(THERMAL_JSON)))  # data: no MES record
        writer.submit(SlotStateChanged(batch, slot, serial, "done"))
        writer.submit(DutVerdict(batch, slot, serial, verdict=verdict))  # the final verdict: the MES record
        time.sleep(rng.uniform(0.005, 0.04))
    writer.close()
    db.dispose()
    print(json.dumps({"station": station, "runs": len(runs), "commits": writer.stats["commits"],
                      "dropped": writer.stats["dropped_events"], "storage_failures": writer.stats["storage_failures"]}))


if __name__ == "__main__":
    main()
