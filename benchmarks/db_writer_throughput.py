"""Database figures: bytes per DUT run of fast-thermal, and write throughput with 64 DUTs.

    .venv/bin/python benchmarks/db_writer_throughput.py [--duts 64] [--url sqlite:///...]

1. Bytes per run: one simulated LIS3DSH fast-thermal log (drivers.sim) written through DbWriter as
   the daemon writes it (blocks of 0.1 s x speed 60, one segment event per segment), then the
   sample-chunk bytes of that run and the whole database file size divided by the runs.
2. Throughput: 64 DUT runs streaming blocks of 20 samples as fast as the writer takes them, for a
   fixed number of blocks; committed samples per second (wall, from first submit to flush), commits
   per second, and the bytes stored per sample. SQLite in WAL mode with synchronous=FULL, on disk.
Prints, never asserts.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from db import Database, DbWriter  # noqa: E402
from db.repository import run_sample_bytes  # noqa: E402
from drivers.sim.physics import draw_population  # noqa: E402
from drivers.sim.profiles import run_profile  # noqa: E402
from drivers.sim.world import SimWorld  # noqa: E402
from contracts.events import SamplesReceived, SegmentLogged  # noqa: E402
from station.science.streaming import StreamingCalibrator  # noqa: E402
from contracts.types import SampleBlock  # noqa: E402


def bytes_per_run(url: str, n_duts: int = 4) -> None:
    world = SimWorld(draw_population(n_duts, 5), seed=5)
    logs = run_profile(world, "fast-thermal")
    db = Database(url)
    db.upgrade()
    batch = db.create_batch("fast-thermal", "bench", {})
    w = DbWriter(db)
    per_block = 19  # 0.1 s reads at speed 60 and 3.125 Hz
    runs = []
    for i, lg in enumerate(logs):
        run = db.create_run(batch, f"s{i}", lg.meta["serial"], "LIS3DSH", {})
        runs.append(run)
        w.bind_run(batch, f"s{i}", run)
        cal = StreamingCalibrator()
        pos = int(lg.position[0]) if lg.position is not None else None
        for k in range(0, len(lg), per_block):
            sl = slice(k, k + per_block)
            b = SampleBlock(lg.time_s[sl], lg.acc_g[sl], lg.temp_c[sl])
            w.submit(SamplesReceived(batch, f"s{i}", lg.meta["serial"], 0, b, position=pos))
            for seg in cal.update_batch(b.time_s, b.acc_g, b.temp_c):
                w.submit(SegmentLogged(batch, f"s{i}", lg.meta["serial"], 0, seg))
    w.close()
    n = len(logs[0])
    sample_bytes = [run_sample_bytes(db, r) for r in runs]
    db.dispose()  # the last connection's close checkpoints the WAL into the file
    path = url.removeprefix("sqlite:///")
    file_bytes = os.path.getsize(path) if os.path.exists(path) else float("nan")
    print(f"fast-thermal run: {n} samples ({logs[0].time_s[-1] / 3600:.2f} h at 3.125 Hz)")
    print(f"  sample chunks: {np.mean(sample_bytes) / 1024:.1f} KiB per run ({np.mean(sample_bytes) / n:.2f} bytes/sample)")
    print(f"  whole SQLite file / runs: {file_bytes / len(runs) / 1024:.1f} KiB per run "
          f"(segments, chunks, indexes; {len(runs)} runs)")


def throughput(url: str, n_duts: int, blocks_per_dut: int) -> None:
    db = Database(url)
    db.upgrade()
    batch = db.create_batch("fast-thermal", "bench", {})
    rng = np.random.default_rng(1)
    w = DbWriter(db)
    runs = []
    for i in range(n_duts):
        run = db.create_run(batch, f"s{i}", f"BENCH{i:04d}", "LIS3DSH", {})
        runs.append(run)
        w.bind_run(batch, f"s{i}", run)
    m = 20
    base = np.round(rng.normal(0.577, 3e-3, (m * 50, 3)) / 60e-6) * 60e-6
    temp = 25.0 + np.round(rng.normal(0, 0.4, m * 50))
    t0 = time.perf_counter()
    total = 0
    for k in range(blocks_per_dut):
        j = (k % 50) * m
        t = (k * m + np.arange(m)) / 3.125
        for i in range(n_duts):
            w.submit(SamplesReceived(batch, f"s{i}", f"BENCH{i:04d}", 0, SampleBlock(t, base[j:j + m], temp[j:j + m]),
                                     position=0))
            total += m
    t_submit = time.perf_counter() - t0
    w.flush()
    wall = time.perf_counter() - t0
    commits = w.stats["commits"]
    w.close()
    stored = sum(run_sample_bytes(db, r) for r in runs)
    print(f"{n_duts} DUTs x {blocks_per_dut} blocks of {m} samples = {total} samples")
    print(f"  submit (event loop side): {total / t_submit:,.0f} samples/s; committed: {total / wall:,.0f} samples/s "
          f"in {wall:.1f} s, {commits} commits ({commits / wall:.1f}/s), {stored / total:.2f} bytes/sample")
    print(f"  = {total / wall / (n_duts * 3.125):,.0f}x the live rate of {n_duts} DUTs at 3.125 Hz")
    db.dispose()


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--duts", type=int, default=64)
    p.add_argument("--blocks", type=int, default=400)
    p.add_argument("--url", default=None, help="database URL (default: a fresh SQLite file in a temp dir)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bytes_per_run(args.url or f"sqlite:///{tmp}/runs.db")
        throughput(args.url or f"sqlite:///{tmp}/tput.db", args.duts, args.blocks)


if __name__ == "__main__":
    main()
