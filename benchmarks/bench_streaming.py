"""Throughput of the streaming calibrator on one core: batched and one sample at a time.

    .venv/bin/python benchmarks/bench_streaming.py [--minutes 90] [--repeat 5]

A synthetic fast-thermal record (LIS3DSH-like, 3.125 Hz, four segments) is tiled to ~1.4 M
samples for the batch path (fed in batches of 4096 and in one call) and run sample by sample
for the scalar path. Prints samples/s; no assertion (speed is not a test).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from station.science.streaming import StreamingCalibrator  # noqa: E402
from thermal_synth import fast_thermal  # noqa: E402


def _tile(rec, times: int):
    n = rec.time_s.shape[0]
    span = rec.time_s[-1] - rec.time_s[0] + 1 / 3.125
    t = np.concatenate([rec.time_s + k * span for k in range(times)])
    return t, np.tile(rec.acc_g, (times, 1)), np.tile(rec.temp_c, times), n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tiles", type=int, default=64, help="copies of the ~21.5 k-sample record")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scalar-samples", type=int, default=200_000)
    args = ap.parse_args()
    rec = fast_thermal(seed=0)
    t, acc, temp, _ = _tile(rec, args.tiles)
    n = t.shape[0]
    for chunk in (4096, 65536, n):
        best = np.inf
        for _ in range(args.repeat):
            cal = StreamingCalibrator()
            t0 = time.perf_counter()
            for i in range(0, n, chunk):
                cal.update_batch(t[i : i + chunk], acc[i : i + chunk], temp[i : i + chunk])
            best = min(best, time.perf_counter() - t0)
        label = "one call" if chunk == n else f"batches of {chunk}"
        print(f"update_batch ({label:>17}): {n / best:12,.0f} samples/s  ({n} samples, {len(cal.segments)} segments)")
    m = min(args.scalar_samples, n)
    tl, accl, templ = t[:m].tolist(), acc[:m], temp[:m].tolist()
    cal = StreamingCalibrator()
    t0 = time.perf_counter()
    for i in range(m):
        cal.update(tl[i], accl[i], templ[i])
    dt = time.perf_counter() - t0
    print(f"update (one sample at a time):  {m / dt:12,.0f} samples/s  ({m} samples, {len(cal.segments)} segments)")


if __name__ == "__main__":
    main()
