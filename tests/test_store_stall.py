"""A store that stalls is a failing store: another PROCESS holds an exclusive lock on the station's
SQLite file for ~30 s while the daemon's events keep coming. The DbWriter's commit blocks inside
SQLite's busy timeout, so only its stall watchdog can tell: within 10 s of the stall's start the
alarm callback (on_storage, which raises the daemon's critical alarm) fires with "stalled: ...",
`writer.failing` is set and the supervisor's storage_status() (what /api/health reports) says
error. Once the lock is released everything submitted is stored (rows counted) and on_storage(None)
reports the recovery. The latency from the lock to the alarm is measured and printed."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from types import SimpleNamespace

from sqlalchemy import func, select

from db import DbWriter
from db.models import DutRun, SampleChunk, SegmentRow
from db_helpers import HOLD_LOCK as LOCKER, lis3dsh_stream, segment, sqlite_db
from contracts.events import DutVerdict, SamplesReceived, SegmentLogged
from station.daemon.supervisor import Station
from contracts.types import SampleBlock

HOLD_S = 30.0
STALL_S = 5.0
ALARM_WITHIN_S = 10.0



def _storage_status(writer: DbWriter, db) -> str:
    """The supervisor's own health logic on this writer (station/daemon/supervisor.py, not a copy)."""
    return Station.storage_status(SimpleNamespace(writer=writer, db=db, storage=SimpleNamespace(probe=None)))


def test_a_commit_stalled_by_another_process_raises_the_storage_alarm_then_recovers(tmp_path):
    db = sqlite_db(tmp_path)
    batch = db.create_batch("fast-thermal", "op", {})
    runs = [db.create_run(batch, f"s{i}", f"STALL{i}", "LIS3DSH", {}) for i in range(3)]
    calls: list[tuple[float, str | None]] = []
    w = DbWriter(db, interval_s=0.05, stall_s=STALL_S, on_storage=lambda reason: calls.append((time.time(), reason)))
    for i, run in enumerate(runs):
        w.bind_run(batch, f"s{i}", run)
    time_s, acc, temp = lis3dsh_stream(9000)  # 45 s of blocks: the producer outlasts the stall
    stop = threading.Event()
    sent = {"blocks": 0, "samples": 0, "segments": 0}

    def daemon_events() -> None:  # what a running batch keeps publishing, 20 blocks a second
        k = 0
        while not stop.is_set() and k + 10 <= len(time_s):
            for i in range(3):
                w.submit(SamplesReceived(batch, f"s{i}", f"STALL{i}", 0,
                                         SampleBlock(time_s[k:k + 10], acc[k:k + 10], temp[k:k + 10])))
                sent["samples"] += 10
            sent["blocks"] += 1
            if sent["blocks"] % 40 == 0:
                w.submit(SegmentLogged(batch, "s0", "STALL0", 0, segment(sent["segments"])))
                sent["segments"] += 1
            k += 10
            time.sleep(0.05)

    producer = threading.Thread(target=daemon_events)
    producer.start()
    time.sleep(1.0)
    assert w.flush(10) and w.failing is None and _storage_status(w, db) == "ok"

    locker = subprocess.Popen([sys.executable, "-c", LOCKER, str(tmp_path / "station.db"), str(HOLD_S)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = locker.stdout.readline().split()
        assert line and line[0] == "LOCKED", locker.stderr.read()
        t_lock = float(line[1])
        t0 = time.monotonic()
        while not calls and time.monotonic() - t0 < ALARM_WITHIN_S + 5:
            time.sleep(0.05)
        assert calls, "no storage alarm while the database was locked"
        t_alarm, reason = calls[0]
        latency_s = t_alarm - t_lock
        health = _storage_status(w, db)
        print(f"\nstall alarm {latency_s:.2f} s after another process locked the database "
              f"(threshold {STALL_S:g} s): {reason!r}; health: {health!r}")
        assert reason is not None and reason.startswith("stalled: a commit has been waiting")
        assert "database locked?" in reason
        assert latency_s <= ALARM_WITHIN_S
        assert w.failing == reason and health.startswith("error: writes failing: stalled")
        w.submit(DutVerdict(batch, "s1", "STALL1", verdict={"verdict": "pass", "grade": "A"}))  # during the stall
        out, err = locker.communicate(timeout=HOLD_S + 30)
        assert "RELEASED" in out, err
        t_release = float(out.split("RELEASED")[1].split()[0])
        stop.set()
        producer.join(10)
        w.submit(DutVerdict(batch, "s2", "STALL2", verdict={"verdict": "fail", "grade": "reject"}))
        assert w.flush(90), "writes did not resume after the lock was released"
        t_stored = time.time()
    finally:
        stop.set()
        if locker.poll() is None:
            locker.kill()
    w.close()
    recovered = [t for t, r in calls if r is None]
    assert recovered and calls[-1][1] is None and w.failing is None and _storage_status(w, db) == "ok"
    print(f"lock held {t_release - t_lock:.1f} s; recovery reported {recovered[0] - t_release:.2f} s after release; "
          f"everything stored {t_stored - t_release:.2f} s after release; storage calls: "
          f"{[(round(t - t_lock, 2), r) for t, r in calls]}")
    with db.session() as s:
        n_samples = s.scalar(select(func.sum(DutRun.n_samples)))
        n_chunk_samples = s.scalar(select(func.sum(SampleChunk.n)))
        n_segments = s.scalar(select(func.count(SegmentRow.id)))
        verdicts = dict(s.execute(select(DutRun.slot, DutRun.verdict)).all())
    assert n_samples == n_chunk_samples == sent["samples"] and n_segments == sent["segments"] > 0
    assert verdicts == {"s0": None, "s1": "pass", "s2": "fail"}
    assert w.stats["dropped_events"] == 0 and w.stats["abandoned_events"] == 0 and w.stats["stalls"] >= 1
    print(f"stored after the stall: {n_samples} samples, {n_segments} segments, 2 verdicts, "
          f"{w.stats['commits']} commits, {w.stats['storage_failures']} failed commit attempts")
