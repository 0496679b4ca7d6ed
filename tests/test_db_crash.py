"""Crash safety building block: a process writing through DbWriter is SIGKILLed mid-stream; every
segment and sample whose commit it acknowledged is in the reopened database, which is intact."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select

from db import Database, codec
from db.export import run_log
from db.models import DutRun, SampleChunk, SegmentRow
from db_helpers import sqlite_db

CHILD = Path(__file__).with_name("db_crash_child.py")
ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("kill_after_commits", [3, 40])
def test_sigkill_mid_stream_loses_nothing_committed(tmp_path, kill_after_commits):
    db = sqlite_db(tmp_path)
    batch = db.create_batch("fast-thermal", "op", {})
    run = db.create_run(batch, "s0", "CRASH1", "LIS3DSH", {}, state="running")
    db.dispose()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, str(CHILD), str(db.engine.url), str(batch), str(run)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    acked_segments: set[int] = set()
    acked_samples = 0
    commits = 0
    try:
        for line in proc.stdout:
            parts = line.split()
            assert parts[0] == "C", line
            acked_samples = int(parts[1])
            acked_segments.update(int(p) for p in parts[2:])
            commits += 1
            if commits >= kill_after_commits:
                os.kill(proc.pid, signal.SIGKILL)  # while the writer keeps committing
                break
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(30)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read()
    assert acked_segments and acked_samples > 0

    db = Database(str(db.engine.url))
    assert db.sqlite_integrity_check() == "ok"
    db.upgrade()
    with db.session() as s:
        stored_segments = set(s.scalars(select(SegmentRow.seg_index).where(SegmentRow.run_id == run)))
        n_samples = s.scalar(select(DutRun.n_samples).where(DutRun.id == run))
        chunk_total = s.scalar(select(func.sum(SampleChunk.n)).where(SampleChunk.run_id == run))
        chunks = s.execute(select(SampleChunk.seq, SampleChunk.n, SampleChunk.data).where(SampleChunk.run_id == run)
                           .order_by(SampleChunk.seq)).all()
    assert acked_segments <= stored_segments
    assert n_samples == chunk_total >= acked_samples  # counters and chunks committed together
    assert all(len(codec.decode(data)) == n for _, n, data in chunks)
    out = run_log(db, run)  # the stream is a gap-free prefix of what the child produced
    assert np.array_equal(out.time_s, np.round(np.arange(len(out)) / 3.125, 6))
    # and the daemon's restart path: running -> interrupted, nothing removed
    db.mark_interrupted()
    rp = db.resume_point(batch)
    assert rp.runs[0].state == "interrupted" and rp.runs[0].n_samples == n_samples
