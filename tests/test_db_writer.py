"""DbWriter (one thread, batched commits, never blocking submit), resume bookkeeping, repository
paging and the MES outbox, against SQLite on disk."""

from __future__ import annotations

import sqlite3
import threading
from datetime import timedelta

import numpy as np
import pytest
from sqlalchemy import func, select

from db import DbWriter
from db import repository as repo
from db.export import run_log
from db.models import Batch, DutRun, Outbox, SampleChunk, SegmentRow, utcnow
from contracts.events import (
    BatchStateChanged, DutResult, DutVerdict, LampChanged, SamplesReceived, SegmentLogged, SlotStateChanged,
    StepStarted,
)
from contracts.run_records import ThermalReport
from contracts.sfem_result import SfemResult
from contracts.logfile import ACC_DECIMALS
from contracts.types import SampleBlock
from db_helpers import SFEM_JSON, THERMAL_JSON, lis3dsh_stream, segment, sqlite_db


def _setup(tmp_path, n_slots=1):
    db = sqlite_db(tmp_path)
    batch = db.create_batch("fast-thermal", "op", {"k": 1})
    runs = [db.create_run(batch, f"s{i}", f"SIM{i:04d}", "LIS3DSH", {"serial": f"SIM{i:04d}"}) for i in range(n_slots)]
    return db, batch, runs


def test_many_events_per_transaction_and_segments_committed_as_they_happen(tmp_path):
    db, batch, runs = _setup(tmp_path, n_slots=8)
    commits = []
    w = DbWriter(db, interval_s=0.2, on_commit=commits.append)
    for i, run in enumerate(runs):
        w.bind_run(batch, f"s{i}", run)
    time_s, acc, temp = lis3dsh_stream(400)
    for k in range(0, 400, 20):
        for i in range(8):
            w.submit(SamplesReceived(batch, f"s{i}", f"SIM{i:04d}", 0, SampleBlock(time_s[k:k + 20], acc[k:k + 20], temp[k:k + 20])))
    w.submit(StepStarted(batch, 1, "P hot", 0, True, None))  # not stored, not an error
    w.submit(LampChanged(batch, True, "step"))
    for i in range(8):
        w.submit(SegmentLogged(batch, f"s{i}", f"SIM{i:04d}", 1, segment(0)))
    assert w.flush(timeout=30)
    # 170 events in a handful of transactions, all stored before the batch ends
    assert w.stats["committed_events"] == 170 and len(commits) <= 4
    assert w.stats["unbound_events"] == 0 and w.stats["dropped_events"] == 0
    assert sum(len(c.segments) for c in commits) == 8
    with db.session() as s:
        assert s.scalar(select(func.count(SegmentRow.id))) == 8
        assert s.scalar(select(func.sum(DutRun.n_samples))) == 8 * 400
        assert s.scalar(select(func.count(SampleChunk.id))) == 8 * len(commits)  # one small chunk per run per commit
    assert len(run_log(db, runs[3])) == 400  # readable while the writer is open (WAL)
    w.close()
    with db.session() as s:  # close sealed the small chunks into one per run
        assert s.scalar(select(func.count(SampleChunk.id))) == 8
        assert s.scalar(select(func.min(SampleChunk.sealed)))


def test_submit_never_blocks_even_when_the_database_is_locked(tmp_path):
    db, batch, runs = _setup(tmp_path)
    w = DbWriter(db, interval_s=0.05)
    w.bind_run(batch, "s0", runs[0])
    locker = sqlite3.connect(str(tmp_path / "station.db"), isolation_level=None)
    locker.execute("BEGIN IMMEDIATE")  # another writer holds the write lock
    time_s, acc, temp = lis3dsh_stream(2000)
    done = threading.Event()

    def producer():
        for k in range(0, 2000, 10):
            w.submit(SamplesReceived(batch, "s0", "SIM0000", 0, SampleBlock(time_s[k:k + 10], acc[k:k + 10], temp[k:k + 10])))
        done.set()

    threading.Thread(target=producer).start()
    assert done.wait(10), "submit() blocked while the database was locked"
    assert not w.flush(timeout=0.5)  # nothing can be committed yet
    locker.execute("ROLLBACK")
    locker.close()
    assert w.flush(timeout=60)
    w.close()
    assert np.array_equal(run_log(db, runs[0]).acc_g, np.round(acc, ACC_DECIMALS))


def test_state_events_results_and_results_since_paging(tmp_path):
    """The MES record is the final verdict (design 8): results are data (no result_seq), each
    DutVerdict is one record, and a second verdict of a run is a new record that supersedes it."""
    db, batch, runs = _setup(tmp_path, n_slots=5)
    w = DbWriter(db, interval_s=0.01)
    for i, run in enumerate(runs):
        w.bind_run(batch, f"s{i}", run)
    w.submit(BatchStateChanged(batch, "running"))
    for i in range(5):
        w.submit(DutResult(batch, f"s{i}", f"SIM{i:04d}", thermal=ThermalReport.from_json(THERMAL_JSON)))
    w.submit(DutResult(batch, "s3", "SIM0003", sfem=SfemResult.from_json(SFEM_JSON)))  # a newer result for run 3: still data only
    w.flush()
    assert repo.results_since(db, 0) == []  # no verdict yet: nothing reaches the MES
    order = [3, 1, 4, 0, 2]
    for i in order:
        w.submit(DutVerdict(batch, f"s{i}", f"SIM{i:04d}", verdict={"verdict": "error", "reason": "interrupted"}))
        w.flush()
    w.submit(SlotStateChanged(batch, "s2", "SIM0002", "faulted", fault_reason="link lost"))
    w.submit(DutVerdict(batch, "s3", "SIM0003", verdict={"verdict": "pass", "grade": "A", "tray": "T1"}))  # re-judged
    w.submit(BatchStateChanged(batch, "finished"))
    w.close()
    page1 = repo.results_since(db, 0, limit=3)
    page2 = repo.results_since(db, page1[-1]["id"], limit=3)
    got = [r["run_id"] for r in page1 + page2]
    assert got == [runs[i] for i in (3, 1, 4, 0, 2, 3)]  # run 3 again at the end: its superseding record
    ids = [r["id"] for r in page1 + page2]
    assert ids == sorted(ids) and len(set(ids)) == 6
    assert repo.results_since(db, ids[-1]) == []
    first, again = page1[0], page2[-1]
    assert (first["revision"], first["supersedes"], first["verdict"]) == (1, None, "error")
    assert (again["revision"], again["supersedes"], again["verdict"]) == (2, first["idempotency_key"], "pass")
    assert [r["revision"] for r in page1 + page2][1:5] == [1, 1, 1, 1]
    assert again["sfem"]["steps"][0]["rmse_after_mg"] == 0.9 and again["thermal"]["x"]["tdb_mg_per_c"] == 0.42
    assert page1[0]["idempotency_key"] == f"result:{runs[3]}:{ids[0]}" and page1[0]["created_at"]
    assert repo.run_detail(db, runs[3])["result_seq"] == ids[-1]  # the run carries its latest record
    audit = [a for a in repo.audit_list(db) if a["action"] == "verdict superseded"]
    assert len(audit) == 1 and audit[0]["detail"]["old"]["result_seq"] == ids[0]
    # one key per record wherever it is named (db/mes_record.py mes_key): the feed, the audit entry
    assert audit[0]["detail"]["old"]["idempotency_key"] == first["idempotency_key"]
    assert audit[0]["detail"]["new"]["idempotency_key"] == again["idempotency_key"]
    assert audit[0]["detail"]["new"]["result_seq"] == ids[-1] and audit[0]["detail"]["new"]["verdict"] == "pass"
    d = repo.batch_detail(db, batch)
    assert d["state"] == "finished" and d["ended_at"] is not None
    assert {r["slot"]: r["state"] for r in d["runs"]}["s2"] == "faulted"
    assert {r["slot"]: r["fault_reason"] for r in d["runs"]}["s2"] == "link lost"
    assert repo.runs_of_dut(db, "SIM0002")[0]["state"] == "faulted"
    assert repo.runs_of_dut(db, "NOPE") is None and repo.dut_by_serial(db, "NOPE") is None
    assert repo.segments_of_run(db, 999) is None and repo.batch_detail(db, 999) is None
    assert [d["serial"] for d in repo.search_duts(db, "sim000")][:1] and len(repo.search_duts(db, "0003")) == 1


def test_unbound_events_fall_back_to_the_batch_slot_run(tmp_path):
    db, batch, runs = _setup(tmp_path)
    w = DbWriter(db)  # no bind_run: the writer finds (batch, slot) in the database
    w.submit(SegmentLogged(batch, "s0", "SIM0000", 0, segment(7)))
    w.submit(SegmentLogged(batch, "nope", "X", 0, segment(8)))
    w.close()
    assert [g["index"] for g in repo.segments_of_run(db, runs[0])] == [7]
    assert w.stats["unbound_events"] == 1


def test_mark_interrupted_and_resume_point(tmp_path):
    db, batch, runs = _setup(tmp_path, n_slots=3)
    db.set_batch_state(batch, "running", step_index=0)
    db.set_run_state(runs[0], "running")
    db.set_run_state(runs[1], "running")
    db.set_run_state(runs[2], "faulted", "no identity")
    w = DbWriter(db, seal_samples=100)
    for i, run in enumerate(runs[:2]):
        w.bind_run(batch, f"s{i}", run)
    time_s, acc, temp = lis3dsh_stream(150)
    for i in range(2):
        w.submit(SamplesReceived(batch, f"s{i}", f"SIM{i:04d}", 0, SampleBlock(time_s[:30], acc[:30], temp[:30])))
        w.submit(SegmentLogged(batch, f"s{i}", f"SIM{i:04d}", 0, segment(0)))
    w.flush()
    db.set_batch_state(batch, "running", step_index=1, completed_step=0)
    done = db.create_batch("fast-thermal", "op", {})
    db.set_batch_state(done, "finished")
    # the process dies here (no close): the next daemon start
    assert db.mark_interrupted() == [batch]
    rp = db.resume_point(batch)
    assert rp.state == "interrupted" and rp.last_completed_step == 0 and rp.next_step == 1 and rp.step_index == 1
    assert rp.config_snapshot == {"k": 1} and rp.profile == "fast-thermal"
    assert [(r.slot, r.state, r.n_samples, r.n_segments) for r in rp.runs] == [
        ("s0", "interrupted", 30, 1), ("s1", "interrupted", 30, 1), ("s2", "faulted", 0, 0)]
    assert rp.runs[0].last_time_s == pytest.approx(time_s[29])
    assert repo.batch_detail(db, done)["state"] == "finished"
    with pytest.raises(KeyError):
        db.resume_point(999)
    # resume: a new writer continues the run's chunk sequence and compacts the old small chunk
    db.set_batch_state(batch, "running", step_index=1)
    db.set_run_state(runs[0], "running")
    w2 = DbWriter(db, seal_samples=100)
    w2.bind_run(batch, "s0", runs[0])
    w2.submit(SamplesReceived(batch, "s0", "SIM0000", 1, SampleBlock(time_s[30:], acc[30:], temp[30:])))
    w2.close()
    assert np.array_equal(run_log(db, runs[0]).time_s, np.round(time_s, 6))
    with db.session() as s:
        rows = s.execute(select(SampleChunk.n, SampleChunk.sealed).where(SampleChunk.run_id == runs[0])).all()
    assert rows == [(150, True)]


def test_outbox_enqueue_pending_delivered_failed(tmp_path):
    db, batch, runs = _setup(tmp_path)
    a = repo.outbox_enqueue(db, "run-1-result-1", {"serial": "SIM0000", "x": np.float64(0.5)})
    assert repo.outbox_enqueue(db, "run-1-result-1", {"other": 1}) == a  # idempotent
    b = repo.outbox_enqueue(db, "run-2-result-2", {"serial": "SIM0001"})
    assert [m["id"] for m in repo.outbox_pending(db)] == [a, b]
    repo.outbox_mark_failed(db, a, "HTTP 503", utcnow() + timedelta(minutes=5))
    repo.outbox_mark_delivered(db, b)
    assert repo.outbox_pending(db) == []
    later = repo.outbox_pending(db, now=utcnow() + timedelta(minutes=6))
    assert [(m["id"], m["attempts"], m["last_error"], m["payload"]["x"]) for m in later] == [(a, 1, "HTTP 503", 0.5)]
    with pytest.raises(KeyError):
        repo.outbox_mark_delivered(db, 999)
    # the writer's transactional outbox (opt-in): the verdict record and its message in one commit;
    # a result alone is data, no MES message
    w = DbWriter(db, outbox=True)
    w.bind_run(batch, "s0", runs[0])
    w.submit(DutResult(batch, "s0", "SIM0000", thermal=ThermalReport.from_json(THERMAL_JSON)))
    assert w.flush(30)
    with db.session() as s:
        assert s.scalar(select(func.count(Outbox.id))) == 2
    w.submit(DutVerdict(batch, "s0", "SIM0000", verdict={"verdict": "pass", "grade": "A"}))
    w.close()
    with db.session() as s:
        keys = list(s.scalars(select(Outbox.idempotency_key).order_by(Outbox.id)))
        assert keys[-1] == f"result:{runs[0]}:1" and len(keys) == 3
        last = s.scalars(select(Outbox).order_by(Outbox.id.desc())).first()
        assert (last.payload["verdict"], last.payload["revision"], last.payload["supersedes"]) == ("pass", 1, None)
        assert s.get(Batch, batch).state == "created"


def test_a_replays_verdict_is_stored_but_never_reaches_the_mes(tmp_path):
    db = sqlite_db(tmp_path)
    batch = db.create_batch("fast-thermal", "op", {}, replay_of="batch 1 of line-A")
    run = db.create_run(batch, "s0", "REPLAY1", "LIS3DSH", {})
    with DbWriter(db, interval_s=0.01) as w:
        w.bind_run(batch, "s0", run)
        w.submit(DutVerdict(batch, "s0", "REPLAY1", verdict={"verdict": "pass", "grade": "A"}))
        w.submit(DutVerdict(batch, "s0", "REPLAY1", verdict={"verdict": "fail", "grade": "reject"}))
    detail = repo.run_detail(db, run)
    assert (detail["verdict"], detail["result_seq"]) == ("fail", None)
    assert repo.results_since(db, 0) == []
    assert [a for a in repo.audit_list(db) if a["action"] == "verdict superseded"] == []
    from db.models import VerdictHistoryRow

    with db.session() as s:
        rows = s.execute(select(VerdictHistoryRow.verdict, VerdictHistoryRow.result_seq, VerdictHistoryRow.supersedes_seq)
                         .order_by(VerdictHistoryRow.id)).all()
    assert [tuple(r) for r in rows] == [("pass", None, None), ("fail", None, None)]


def test_upgrade_from_0006_keeps_every_record_in_the_feed(tmp_path):
    """Migration 0007 makes every run that had a result_seq revision 1 of its run."""
    from alembic import command
    from sqlalchemy import text

    from db import Database

    db = Database(f"sqlite:///{tmp_path / 'old.db'}")
    with db.engine.begin() as conn:
        command.upgrade(db._alembic_config(conn), "0006")
    # rows written as a 0006 station wrote them (the ORM of this software knows later columns)
    with db.engine.begin() as conn:
        conn.execute(text("INSERT INTO batch (id, profile, station, operator, state, reason, config_snapshot, step_windows, "
                          "schema_version, created_at) VALUES (1, 'fast-thermal', '', 'op', 'finished', '', '{}', '{}', "
                          "'0006', '2026-11-01 10:00:00')"))
        for i in range(3):
            conn.execute(text("INSERT INTO dut (id, serial, sensor, first_seen, last_seen) VALUES "
                              "(:i, :s, 'LIS3DSH', '2026-11-01 10:00:00', '2026-11-01 10:00:00')"), {"i": i + 1, "s": f"OLD{i}"})
            conn.execute(text("INSERT INTO dut_run (id, batch_id, slot, station, dut_id, state, fault_reason, identity, "
                              "n_samples, lost_samples, started_at, attempt, verdict_reason) VALUES "
                              "(:i, 1, :slot, '', :i, 'done', '', '{}', 0, 0, '2026-11-01 10:00:00', 1, '')"),
                         {"i": i + 1, "slot": f"s{i}"})
        runs = [1, 2, 3]
        conn.execute(text("UPDATE dut_run SET result_seq = 7, verdict = 'pass', grade = 'A' WHERE id = :r"), {"r": runs[0]})
        conn.execute(text("UPDATE dut_run SET result_seq = 9 WHERE id = :r"), {"r": runs[2]})  # a result, no verdict
    assert db.upgrade() == db.head_revision()
    got = [(r["id"], r["run_id"], r["revision"], r["supersedes"], r["verdict"]) for r in repo.results_since(db, 0)]
    assert got == [(7, runs[0], 1, None, "pass"), (9, runs[2], 1, None, None)]
