"""Replay rate: N DUTs of design-5.1 logs through `station replay`'s runner, samples per second.

    .venv/bin/python benchmarks/replay_rate.py --duts 64 --speed 2000

The logs come from tests/replay_logs.py (a generator independent of the station's simulator);
every DUT is a simulated serial board on its own pty, the daemon is the real one, the database
SQLite in a temporary folder. Prints the wall time, samples sent, samples/s and the comparison
summary (every DUT should be unchanged against the offline fit of its log).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duts", type=int, default=64)
    ap.add_argument("--speed", type=float, default=2000.0)
    args = ap.parse_args()
    from replay_logs import write_logs

    from station.replay.recording import from_logs
    from station.replay.runner import ReplayOptions, run_replay

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.monotonic()
        paths, _ = write_logs(Path(tmp) / "logs", args.duts)
        rec = from_logs(paths, "fast-thermal")
        t_load = time.monotonic() - t0
        opts = ReplayOptions(db_url=f"sqlite:///{Path(tmp) / 'replay.db'}", speed=args.speed)
        diff = asyncio.run(run_replay(rec, opts))
    rate = diff.agreement.get("rate", {})
    s = diff.summary()
    n_rec = sum(len(d) for d in rec.duts)
    print(f"{args.duts} DUTs, speed x{args.speed:g}: logs written and loaded in {t_load:.1f} s")
    print(f"replay: {rate.get('samples_sent')} of {n_rec} recorded samples in {rate.get('wall_s')} s wall "
          f"= {rate.get('samples_per_s')} samples/s; batch {diff.replay_state} {diff.replay_error or ''}")
    for d in diff.duts[:3]:
        print(f"  {d.slot} {d.serial}: {d.note}")
    print(f"outcome: {s['unchanged']} unchanged, {s['changed']} changed; samples identical: "
          f"{sum(bool(d.samples_identical) for d in diff.duts)}/{len(diff.duts)}")
    return 0 if diff.replay_state == "finished" and not diff.changed else 1


if __name__ == "__main__":
    raise SystemExit(main())
