"""The writer's events into the database within ONE transaction: which event goes to which rows.

Why a module of its own: db/writer.py decides when a transaction happens (batching, retry, journal,
watchdog); this module decides what it contains, given an open connection: the run an event belongs
to, the rows of segments, results, program-and-verify, states and step windows, the sample chunks
(db/sample_chunks.py), and the verdict records. Row shapes are db/event_rows.py; the MES record's
cursor and key are db/mes_record.py.

The MES record is the run's FINAL verdict (design 8, docs/verdicts.md): only a DutVerdict takes a
result_seq, taken last in the transaction (take_result_seq holds the counter's row lock until the
commit, so the order of result_seq is the commit order even with several stations on one database).
Results (DutResult: thermal/SFEM) and program-and-verify records (DutProgrammed, DutVerified) are
stored as data only: no result_seq, no MES message. A DutVerdict for a run that already has a
result_seq (a resumed batch judged again, a re-judge) is a new record that supersedes the old one:
a new result_seq, the run's verdict columns replaced, and an audit entry. Every DutVerdict writes
its row in verdict_history (the feed pages over it: every record reaches the MES once). A replay's
verdict (batch.replay_of) is stored without a result_seq: it never reaches the MES.

With outbox=True the verdict record's MES message also goes into the outbox table in the same
transaction; off by default because the web's MES worker copies results_since into the outbox
itself (two copies would reach the MES under two keys).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import insert, select, update
from sqlalchemy.engine import Connection

from contracts.events import (
    BatchStateChanged,
    DutProgrammed,
    DutResult,
    DutVerdict,
    DutVerified,
    Event,
    SamplesReceived,
    SegmentLogged,
    SlotStateChanged,
    StepCompleted,
    StepStarted,
)
from db.database import BATCH_END_STATES, RUN_END_STATES, Database
from db.event_rows import (
    outbox_payload,
    program_verify_defaults,
    program_verify_values,
    segment_values,
    sfem_rows,
    step_windows,
    superseded_detail,
    thermal_rows,
    verdict_columns,
)
from db.mes_record import mes_key, revision_of, take_result_seq
from db.models import (
    Batch,
    DutRun,
    Outbox,
    ProgramVerifyRow,
    SegmentRow,
    SfemResultRow,
    ThermalResultRow,
    VerdictHistoryRow,
    utcnow,
)
from db.queries_audit import audit_append
from db.sample_chunks import SampleChunks

log = logging.getLogger("db.writer")  # the writer's log, whichever of its modules speaks

AUDIT_VERDICT_SUPERSEDED = "verdict superseded"  # the audit action of a verdict record replaced by a newer one

STORED = (SamplesReceived, SegmentLogged, DutResult, DutVerdict, SlotStateChanged, BatchStateChanged, StepStarted,
          StepCompleted, DutProgrammed, DutVerified)
BATCH_LEVEL = (BatchStateChanged, StepStarted, StepCompleted)

# stores a verdict once its result_seq is taken (None: a replay's verdict, no MES record)
VerdictFinish = Callable[[Connection, int | None], None]


@dataclass
class CommitInfo:
    """What one writer transaction made durable (passed to `on_commit`)."""

    n_events: int
    n_samples: int
    segments: list[tuple[int, int, int]]  # (run_id, segment index, row id)
    results: list[tuple[int, int]]  # (run_id, result_seq)


class EventStore:
    """Applies events to an open transaction. The run each (batch, slot) belongs to and whether a
    batch is a replay are cached here; `chunks` is the per-run sample chunk bookkeeping, which the
    writer snapshots before a transaction and restores when it fails."""

    def __init__(self, database: Database, station: str, seal_samples: int, outbox: bool,
                 on_unbound: Callable[[], None]) -> None:
        self.db = database
        self.station = station  # stamped on every result row
        self.outbox = outbox
        self.chunks = SampleChunks(seal_samples)  # db/sample_chunks.py
        self._on_unbound = on_unbound  # an event with no run to store it in (counted by the writer)
        self._runs: dict[tuple[int, str | None], int] = {}
        self._replay: dict[int, bool] = {}  # batch id -> is a replay (its results get no result_seq)
        self._runs_lock = threading.Lock()

    def bind_run(self, batch_id: int, slot: str, run_id: int) -> None:
        with self._runs_lock:
            self._runs[(batch_id, slot)] = run_id

    def apply(self, conn: Connection, events: list[Event], seal_all: bool, info: CommitInfo) -> None:
        """Store `events` in the transaction of `conn`; what became durable goes into `info`."""
        samples: dict[int, list[SamplesReceived]] = {}
        seal: set[int] = set()
        # verdicts take their result_seq last (take_result_seq), so the counter's row lock
        # is held only for the commit, not while samples are compressed
        numbered: list[tuple[int, int, VerdictFinish]] = []
        for ev in events:
            if not isinstance(ev, STORED):
                continue  # prompts, lamp, alarms, steps: not stored
            if isinstance(ev, SlotStateChanged) and not ev.batch_id:
                continue  # a slot's state between batches (connect, identify): no run to store it in
            run_id = None if isinstance(ev, BATCH_LEVEL) else self._run_id(conn, ev)
            if isinstance(ev, SamplesReceived):
                if run_id is not None:
                    samples.setdefault(run_id, []).append(ev)
            elif isinstance(ev, SegmentLogged):
                if run_id is not None:
                    info.segments.append((run_id, ev.segment.index, self._segment(conn, run_id, ev)))
            elif isinstance(ev, DutResult):
                if run_id is not None:
                    self._result(conn, run_id, ev)
            elif isinstance(ev, DutVerdict):
                if run_id is not None:
                    numbered.append((ev.batch_id, run_id, self._verdict(conn, run_id, ev)))
            elif isinstance(ev, (DutProgrammed, DutVerified)):
                if run_id is not None:
                    self._program_verify(conn, run_id, ev)
            elif isinstance(ev, SlotStateChanged):
                if run_id is not None:
                    self._slot_state(conn, run_id, ev)
                    if ev.state in RUN_END_STATES:
                        seal.add(run_id)
            elif isinstance(ev, BatchStateChanged):
                seal.update(self._batch_state(conn, ev))
            elif isinstance(ev, StepStarted):
                conn.execute(update(Batch).where(Batch.id == ev.batch_id).values(step_index=ev.step_index))
            elif isinstance(ev, StepCompleted):
                self._step_completed(conn, ev)
        if samples:
            info.n_samples += self.chunks.store(conn, samples, seal)
        self.chunks.seal(conn, sorted(seal | (set(self.chunks.bufs) if seal_all else set())))
        for run_id in seal:  # an ended run's buffer leaves memory (a resumed run reads it back from its rows)
            self.chunks.bufs.pop(run_id, None)
        for batch_id, run_id, finish in numbered:
            if self._is_replay(conn, batch_id):  # a replay's verdicts never reach the MES
                finish(conn, None)
                continue
            seq = take_result_seq(conn)
            finish(conn, seq)
            info.results.append((run_id, seq))

    def _is_replay(self, conn: Connection, batch_id: int) -> bool:
        if batch_id not in self._replay:
            self._replay[batch_id] = conn.execute(
                select(Batch.replay_of).where(Batch.id == batch_id)).scalar() is not None
        return self._replay[batch_id]

    def _run_id(self, conn: Connection, ev: Event) -> int | None:
        slot: str | None = getattr(ev, "slot", None)
        key = (ev.batch_id, slot)
        with self._runs_lock:
            run_id = self._runs.get(key)
        if run_id is None:
            run_id = conn.execute(
                select(DutRun.id).where(DutRun.batch_id == ev.batch_id, DutRun.slot == slot).order_by(DutRun.id.desc())
            ).scalars().first()
            if run_id is None:
                self._on_unbound()
                # a slot's state before its board identified (connecting) has no run yet: expected
                level = logging.DEBUG if isinstance(ev, SlotStateChanged) else logging.WARNING
                log.log(level, "db writer: no run for batch %s slot %s; %s dropped", ev.batch_id, slot, ev.kind)
                return None
            with self._runs_lock:
                self._runs.setdefault(key, run_id)
        return run_id

    def _segment(self, conn: Connection, run_id: int, ev: SegmentLogged) -> int:
        return int(conn.execute(insert(SegmentRow).values(**segment_values(run_id, ev, utcnow())))
                   .inserted_primary_key[0])

    def _result(self, conn: Connection, run_id: int, ev: DutResult) -> None:
        """The analysis' results (thermal, SFEM): data only. No result_seq, no MES message: the
        record the MES gets is the run's final verdict (DutVerdict)."""
        now = utcnow()
        for row in thermal_rows(ev.thermal):
            conn.execute(insert(ThermalResultRow).values(run_id=run_id, station=self.station, created_at=now, **row))
        for row in sfem_rows(ev.sfem):
            conn.execute(insert(SfemResultRow).values(run_id=run_id, station=self.station, created_at=now, **row))

    def _verdict(self, conn: Connection, run_id: int, ev: DutVerdict) -> VerdictFinish:
        """The run's final verdict: one MES record. Returns what stores it once its result_seq is
        taken (at the end of the transaction; None for a replay)."""
        now = utcnow()
        return lambda conn, seq: self._store_verdict(conn, run_id, ev, seq, now)

    def _store_verdict(self, conn: Connection, run_id: int, ev: DutVerdict, seq: int | None, now: datetime) -> None:
        """The verdict columns of the run, its verdict_history row and, when it replaces a record
        the MES already has a number for, the audit entry of the supersession."""
        verdict = dict(ev.verdict or {})
        old = conn.execute(select(DutRun.result_seq, DutRun.verdict, DutRun.grade, DutRun.tray, DutRun.verdict_reason)
                           .where(DutRun.id == run_id)).first()
        supersedes = old.result_seq if (old is not None and seq is not None) else None
        cols = verdict_columns(verdict)
        values: dict[str, object] = {**cols, "judged_at": now}
        if seq is not None:
            values["result_seq"] = seq
        conn.execute(update(DutRun).where(DutRun.id == run_id).values(**values))
        conn.execute(insert(VerdictHistoryRow).values(
            run_id=run_id, result_seq=seq, station=self.station, verdict=cols["verdict"], grade=cols["grade"],
            tray=cols["tray"], reason=cols["verdict_reason"], detail=cols["verdict_detail"],
            limits_name=cols["limits_name"], limits_version=cols["limits_version"], judged_at=now,
            supersedes_seq=supersedes))
        if supersedes is not None and old is not None and seq is not None:
            before: dict[str, object] = {"result_seq": old.result_seq, "verdict": old.verdict, "grade": old.grade,
                                         "tray": old.tray, "verdict_reason": old.verdict_reason}
            self._audit_superseded(conn, run_id, ev, before, supersedes, seq, cols)
        if self.outbox and seq is not None:
            self._outbox_verdict(conn, run_id, ev, seq, supersedes, now)

    def _audit_superseded(self, conn: Connection, run_id: int, ev: DutVerdict, old: Mapping[str, object], old_seq: int,
                          seq: int, cols: dict[str, object]) -> None:
        detail = superseded_detail(run_id, ev, old, mes_key(run_id, old_seq), seq, mes_key(run_id, seq), cols)
        audit_append(self.db, "station", AUDIT_VERDICT_SUPERSEDED, f"run {run_id} ({ev.serial or '-'})", detail,
                     station=self.station, conn=conn)

    def _outbox_verdict(self, conn: Connection, run_id: int, ev: DutVerdict, seq: int, supersedes: int | None,
                        now: datetime) -> None:
        revision = int(conn.execute(select(revision_of(run_id, seq))).scalar_one())
        payload = outbox_payload(run_id, ev, seq, revision, None if supersedes is None else mes_key(run_id, supersedes))
        conn.execute(insert(Outbox).values(
            idempotency_key=mes_key(run_id, seq), topic="result", payload=payload, attempts=0,
            next_attempt_at=now, last_error="", created_at=now,
        ))

    def _program_verify(self, conn: Connection, run_id: int, ev: DutProgrammed | DutVerified) -> None:
        """Upsert the run's program_verify row: data only (the verdict, at the run's end, is the
        record the MES gets)."""
        now = utcnow()
        row = conn.execute(select(ProgramVerifyRow.id).where(ProgramVerifyRow.run_id == run_id)).scalar()
        values = program_verify_values(ev, now)
        if row is None:
            conn.execute(insert(ProgramVerifyRow).values(run_id=run_id, station=self.station,
                                                         **{**program_verify_defaults(now), **values}))
        else:
            conn.execute(update(ProgramVerifyRow).where(ProgramVerifyRow.id == row).values(**values))

    def _slot_state(self, conn: Connection, run_id: int, ev: SlotStateChanged) -> None:
        values: dict[str, object] = {"state": ev.state, "fault_reason": ev.fault_reason}
        values["ended_at"] = utcnow() if ev.state in RUN_END_STATES else None  # None: resumed
        conn.execute(update(DutRun).where(DutRun.id == run_id).values(**values))

    def _step_completed(self, conn: Connection, ev: StepCompleted) -> None:
        """The resume point: committed after (or with) every sample and segment of the step."""
        windows = conn.execute(select(Batch.step_windows).where(Batch.id == ev.batch_id)).scalar()
        conn.execute(
            update(Batch)
            .where(Batch.id == ev.batch_id)
            .values(last_completed_step=ev.step_index, step_windows=step_windows(windows, ev))
        )

    def _batch_state(self, conn: Connection, ev: BatchStateChanged) -> set[int]:
        values: dict[str, object] = {"state": ev.state}
        if ev.reason:
            values["reason"] = ev.reason
        values["ended_at"] = utcnow() if ev.state in BATCH_END_STATES else None  # None: resumed
        conn.execute(update(Batch).where(Batch.id == ev.batch_id).values(**values))
        if ev.state not in BATCH_END_STATES:
            return set()
        return set(conn.execute(select(DutRun.id).where(DutRun.batch_id == ev.batch_id)).scalars())


__all__ = ["EventStore", "CommitInfo", "STORED", "AUDIT_VERDICT_SUPERSEDED"]
