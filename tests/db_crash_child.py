"""Child process of test_db_crash.py: streams samples and segments through DbWriter and prints,
after every commit, what that commit made durable. The parent SIGKILLs it mid-stream."""

from __future__ import annotations

import sys
import time

import numpy as np

from db import Database, DbWriter
from contracts.events import SamplesReceived, SegmentLogged
from contracts.types import SampleBlock, Segment

url, batch, run = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
db = Database(url)
total = 0


def on_commit(info) -> None:
    global total
    total += info.n_samples
    segs = " ".join(str(idx) for _, idx, _ in info.segments)
    sys.stdout.write(f"C {total} {segs}\n")
    sys.stdout.flush()


w = DbWriter(db, interval_s=0.02, seal_samples=256, on_commit=on_commit)
w.bind_run(batch, "s0", run)
rng = np.random.default_rng(0)
n = 0
for k in range(1_000_000):
    m = 20
    t = (n + np.arange(m)) / 3.125
    acc = np.round(rng.normal(0.577, 2e-4, (m, 3)) / 60e-6) * 60e-6
    temp = 25.0 + np.round(rng.normal(0, 0.3, m))
    w.submit(SamplesReceived(batch, "s0", "CRASH1", 0, SampleBlock(t, acc, temp), position=0))
    n += m
    w.submit(SegmentLogged(batch, "s0", "CRASH1", 0, Segment(k, 0, m, t[0], t[-1], (0.577,) * 3, (1e-4,) * 3, 25.0, 0.3, 0)))
    time.sleep(0.002)
