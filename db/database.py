"""The Database class: sessions and the daemon's synchronous bookkeeping calls.

Why: the daemon needs a few small writes it must have an id or an answer back from at once (a
batch, a run numbered as its serial's next attempt, a state, where an interrupted batch stopped);
those are here. Bulk data (samples, segments, results, verdicts) goes through db.writer.DbWriter
off the event loop, and the read side is db/repository.py.

SQLite by default (one file, WAL, foreign keys on), any SQLAlchemy URL otherwise: the same code runs
on PostgreSQL. Where the rest lives (still importable from here):
    db/engine.py   engines and URLs (SQLite pragmas and durability, PostgreSQL timeouts),
                   insert_ignore and retry_collisions (several stations on one database)
    db/schema.py   migrations and the schema/integrity checks (Database.upgrade, check, ...)
"""

from __future__ import annotations

import logging
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterator

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.sql.elements import ColumnElement

from contracts.types import NotFound
from contracts.trace import Trace
from db.engine import (
    SQLITE_SYNCHRONOUS,
    insert_ignore,
    make_engine,
    make_read_only_engine,
    plain_url,
    retry_collisions,
)
from db.models import NO_ATTEMPT, SCHEMA_REVISION, Batch, Dut, DutRun, MeasuredBy, SampleChunk, SegmentRow, utcnow
from db.schema import Schema

if TYPE_CHECKING:
    from db.file_guard import StoreFile

log = logging.getLogger(__name__)

BATCH_ACTIVE_STATES = ("created", "running", "paused")
BATCH_END_STATES = ("finished", "aborted", "failed", "interrupted")
RUN_ACTIVE_STATES = ("connecting", "identified", "running")
RUN_END_STATES = ("done", "faulted", "interrupted")


@dataclass
class RunPoint:
    run_id: int
    slot: str
    serial: str
    sensor: str
    state: str
    fault_reason: str
    identity: dict
    n_samples: int
    n_segments: int
    last_time_s: float | None
    label_serial: str | None = None


@dataclass
class ResumePoint:
    """Where a batch stopped: resume at `next_step` (last_completed_step + 1, 0 if none)."""

    batch_id: int
    profile: str
    operator: str
    state: str
    step_index: int | None
    last_completed_step: int | None
    config_snapshot: dict
    runs: list[RunPoint] = field(default_factory=list)
    step_windows: dict = field(default_factory=dict)  # {"<step>": {"<slot>": [from_s, to_s]}}

    @property
    def next_step(self) -> int:
        return 0 if self.last_completed_step is None else self.last_completed_step + 1


class Database(Schema):
    """The station database: `Database(url)`, then `.upgrade()` (or `.check()`) before use."""

    def __init__(self, url: str, echo: bool = False, station: str = "", read_only: bool = False) -> None:
        self.url = url
        # this station's name (config `name`): stamped on its batches, runs and results; the
        # restart bookkeeping (mark_interrupted, interrupted_batches) touches only its own batches
        self.station = station
        self.read_only = read_only  # a replay's source: read, never migrated or created
        self.collision_retries = 0  # create_run calls retried after a unique collision (see retry_collisions)
        self.engine = make_read_only_engine(url) if read_only else make_engine(url, echo=echo)
        self.Session = sessionmaker(self.engine, expire_on_commit=False)
        # the SQLite file's watch and marker (db/file_guard.py), set by station/daemon/storage.py
        # open_database: the marker is kept up to date with every batch made here
        self.file_guard: StoreFile | None = None
        # the folder of a temporary database (no URL configured: station/daemon/storage.py
        # open_database sets it), kept with this object so it is removed with it
        self.temporary_dir: tempfile.TemporaryDirectory[str] | None = None

    def dispose(self) -> None:
        self.engine.dispose()

    close = dispose

    def __repr__(self) -> str:
        return f"Database({self.engine.url.render_as_string(hide_password=True)!r})"

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A session in a transaction: committed on success, rolled back on error."""
        with self.Session() as s, s.begin():
            yield s

    # ---- batches and runs (the daemon's synchronous calls) ---------------------------------
    def create_batch(self, profile: str, operator: str, config_snapshot: dict[str, object], state: str = "created",
                     replay_of: str | None = None, trace: Trace | None = None) -> int:
        trace = trace or Trace()
        with self.session() as s:
            b = Batch(
                **trace.fields(),
                labels=dict(trace.labels) or None,
                station=self.station,
                replay_of=replay_of or None,
                profile=profile,
                operator=operator,
                state=state,
                config_snapshot=dict(config_snapshot or {}),
                schema_version=SCHEMA_REVISION,
            )
            s.add(b)
            s.flush()
            batch_id = int(b.id)
        if self.file_guard is not None:
            try:
                self.file_guard.write_marker(*self.batch_counts())
            except Exception:  # noqa: BLE001 - the batch exists; the marker is the next start's check
                log.warning("database marker not updated", exc_info=True)
        return batch_id

    def batch_counts(self) -> tuple[int, int]:
        """(how many batches, the highest batch id): what the file's marker remembers."""
        with self.session() as s:
            n, top = s.execute(select(func.count(Batch.id), func.coalesce(func.max(Batch.id), 0))).one()
            return int(n), int(top)

    def set_batch_state(
        self,
        batch_id: int,
        state: str,
        step_index: int | None = None,
        completed_step: int | None = None,
        reason: str | None = None,
    ) -> None:
        """Record the batch state; `completed_step` is what resume restarts after."""
        values: dict[str, object] = {"state": state}
        if step_index is not None:
            values["step_index"] = step_index
        if completed_step is not None:
            values["last_completed_step"] = completed_step
        if reason is not None:
            values["reason"] = reason
        if state in BATCH_END_STATES:
            values["ended_at"] = utcnow()
        elif state in BATCH_ACTIVE_STATES:
            values["ended_at"] = None
        with self.session() as s:
            res = s.execute(update(Batch).where(Batch.id == batch_id).values(**values))
            if res.rowcount == 0:
                raise NotFound(f"no batch {batch_id}")

    def upsert_dut(self, s: Session, serial: str, sensor: str = "") -> Dut:
        """The DUT row of `serial`, made if new: insert-or-get by the database itself (INSERT ...
        ON CONFLICT DO NOTHING, then the row), so two stations meeting the same new serial at the
        same moment both get the one row; never a select-then-insert that loses the race with a
        UniqueViolation. The UPDATE of last_seen row-locks the DUT until the caller's transaction
        ends: run creation for one serial is serialised across stations (create_run counts
        attempts under that lock)."""
        now = utcnow()
        s.execute(insert_ignore(s, Dut, ["serial"]).values(serial=serial, sensor=sensor or "", first_seen=now,
                                                             last_seen=now))
        values: dict[str, object] = {"last_seen": now}
        if sensor:
            values["sensor"] = sensor
        s.execute(update(Dut).where(Dut.serial == serial).values(**values).execution_options(synchronize_session=False))
        return s.scalars(select(Dut).where(Dut.serial == serial).execution_options(populate_existing=True)).one()

    def create_run(
        self, batch_id: int, slot: str, serial: str, sensor: str = "", identity: dict[str, object] | None = None,
        state: str = "identified", *, counts_as_attempt: bool = True, measured_by: MeasuredBy | None = None,
        route_check: str | None = None, route_reason: str = "",
    ) -> int:
        """A new run of `serial` in (batch_id, slot), numbered as the serial's next attempt. Safe with
        several stations on one database: the DUT row is insert-or-get and row-locked while the
        attempt is counted (attempts of real batches are 1..N without duplicates or gaps), and a
        unique collision or a PostgreSQL serialization failure/deadlock is retried.

        counts_as_attempt=False: a run that never tested the part (the label scanned for the slot
        is not the board's serial: station/daemon/slots.py stops it before any data). It is stored
        with attempt 0 (NO_ATTEMPT) so the MES and the history see which board was there, and it
        is no attempt of `serial`: never counted in its attempt numbers, attempts or yields.
        measured_by: the software, firmware and holder that measure the run (None: not known).
        route_check / route_reason: the MES's route check of the part (allowed, refused, unanswered;
        None: none was asked) and its words."""
        return retry_collisions(lambda: self._create_run(batch_id, slot, serial, sensor, identity, state,
                                                         counts_as_attempt, measured_by or MeasuredBy(),
                                                         route_check, route_reason),
                                f"create run of {serial}", on_retry=self._count_retry)

    def _count_retry(self) -> None:
        self.collision_retries += 1

    def _create_run(self, batch_id: int, slot: str, serial: str, sensor: str, identity: dict[str, object] | None,
                    state: str, counts_as_attempt: bool = True, measured_by: MeasuredBy = MeasuredBy(),
                    route_check: str | None = None, route_reason: str = "") -> int:
        with self.session() as s:
            dut = self.upsert_dut(s, serial, sensor)
            # a serial seen again is a retest: its attempt number counts every earlier run of real
            # parts that tested it (a replay re-runs a recorded attempt: it keeps that attempt's
            # number; a run stopped for a label mismatch is no attempt)
            real = select(Batch.id).where(Batch.replay_of.is_(None))
            earlier = int(s.scalar(select(func.count(DutRun.id)).where(
                DutRun.dut_id == dut.id, DutRun.batch_id.in_(real), DutRun.attempt > NO_ATTEMPT)) or 0)
            attempt = earlier + 1
            if s.scalar(select(Batch.replay_of).where(Batch.id == batch_id)) is not None:
                attempt = max(1, earlier)
            if not counts_as_attempt:
                attempt = NO_ATTEMPT
            labels = s.scalar(select(Batch.labels).where(Batch.id == batch_id)) or {}
            run = DutRun(batch_id=batch_id, station=self.station, slot=slot, dut_id=dut.id, state=state, identity=dict(identity or {}),
                         attempt=attempt, label_serial=labels.get(slot) or None, **measured_by.columns(),
                         route_check=route_check, route_reason=route_reason)
            s.add(run)
            s.flush()
            return run.id

    def run_attempt(self, run_id: int) -> int:
        """The attempt number of a run (1 = first test of its serial)."""
        with self.session() as s:
            a = s.scalar(select(DutRun.attempt).where(DutRun.id == run_id))
            if a is None:
                raise NotFound(f"no run {run_id}")
            return int(a)

    def set_run_state(self, run_id: int, state: str, fault_reason: str = "") -> None:
        values: dict[str, object] = {"state": state, "fault_reason": fault_reason}
        if state in RUN_END_STATES:
            values["ended_at"] = utcnow()
        with self.session() as s:
            res = s.execute(update(DutRun).where(DutRun.id == run_id).values(**values))
            if res.rowcount == 0:
                raise NotFound(f"no run {run_id}")

    # ---- resume ----------------------------------------------------------------------------
    def mark_interrupted(self, reason: str = "station restarted") -> list[int]:
        """At daemon start: whatever was running when the last process died is interrupted.
        Only this station's states change (other stations may be running batches in the same
        database); every committed sample, segment and result stays. Returns the ids of
        the interrupted batches."""
        now = utcnow()
        with self.session() as s:
            ids = list(s.scalars(select(Batch.id).where(Batch.state.in_(BATCH_ACTIVE_STATES), self._mine(Batch))
                                 .order_by(Batch.id)))
            if ids:
                s.execute(
                    update(Batch).where(Batch.id.in_(ids)).values(state="interrupted", reason=reason, ended_at=now)
                )
            s.execute(
                update(DutRun)
                .where(DutRun.state.in_(RUN_ACTIVE_STATES), self._mine(DutRun))
                .values(state="interrupted", fault_reason=reason, ended_at=now)
            )
        return ids

    def unjudged_runs(self, exclude_batches: list[int]) -> dict[int, list[int]]:
        """Runs of this station that ended with no verdict stored (the verdict was lost: a
        station stopped while neither the database nor its journal took it), in ended batches of
        real parts, not in `exclude_batches` (the batches this start marked interrupted: judged
        there). Only runs this software line made (software_version set): older runs predate
        verdicts and must not reach the MES now. {batch id: [run ids]}."""
        with self.session() as s:
            rows = s.execute(
                select(DutRun.batch_id, DutRun.id).join(Batch, Batch.id == DutRun.batch_id)
                .where(DutRun.verdict.is_(None), DutRun.state.in_(RUN_END_STATES), DutRun.attempt > NO_ATTEMPT,
                       DutRun.software_version.is_not(None), Batch.replay_of.is_(None),
                       Batch.state.in_(BATCH_END_STATES), self._mine(DutRun),
                       Batch.id.not_in([int(b) for b in exclude_batches] or [-1]))
                .order_by(DutRun.id)).all()
        out: dict[int, list[int]] = {}
        for bid, rid in rows:
            out.setdefault(int(bid), []).append(int(rid))
        return out

    def batch_trace(self, batch_id: int) -> Trace:
        """The work order, part, lot and label serials a batch was started with."""
        with self.session() as s:
            b = s.get(Batch, batch_id)
            if b is None:
                raise NotFound(f"no batch {batch_id}")
            return Trace.of(b)

    def resume_point(self, batch_id: int) -> ResumePoint:
        """What the daemon needs to resume a batch: its last completed step and its runs."""
        with self.session() as s:
            b = s.get(Batch, batch_id)
            if b is None:
                raise NotFound(f"no batch {batch_id}")
            nseg = (
                select(SegmentRow.run_id, func.count(SegmentRow.id).label("n"))
                .group_by(SegmentRow.run_id)
                .subquery()
            )
            tlast = (
                select(SampleChunk.run_id, func.max(SampleChunk.t_last_s).label("t"))
                .group_by(SampleChunk.run_id)
                .subquery()
            )
            rows = s.execute(
                select(DutRun, Dut.serial, Dut.sensor, nseg.c.n, tlast.c.t)
                .join(Dut, Dut.id == DutRun.dut_id)
                .outerjoin(nseg, nseg.c.run_id == DutRun.id)
                .outerjoin(tlast, tlast.c.run_id == DutRun.id)
                .where(DutRun.batch_id == batch_id)
                .order_by(DutRun.id)
            ).all()
            runs = [
                RunPoint(
                    run_id=r.id,
                    slot=r.slot,
                    serial=serial,
                    sensor=sensor,
                    state=r.state,
                    fault_reason=r.fault_reason,
                    identity=dict(r.identity or {}),
                    n_samples=int(r.n_samples),
                    n_segments=int(n or 0),
                    last_time_s=t,
                    label_serial=r.label_serial,
                )
                for r, serial, sensor, n, t in rows
            ]
            return ResumePoint(
                batch_id=b.id,
                profile=b.profile,
                operator=b.operator,
                state=b.state,
                step_index=b.step_index,
                last_completed_step=b.last_completed_step,
                config_snapshot=dict(b.config_snapshot or {}),
                runs=runs,
                step_windows=dict(b.step_windows or {}),
            )

    def interrupted_batches(self) -> list[int]:
        with self.session() as s:
            return list(s.scalars(select(Batch.id).where(Batch.state == "interrupted", self._mine(Batch))
                                  .order_by(Batch.id)))

    def _mine(self, model: type[Batch] | type[DutRun]) -> ColumnElement[bool]:
        """Rows of this station; rows from before migration 0005 (station '') count as anyone's,
        so a single station upgraded in place still resumes its old batch."""
        return model.station.in_([self.station, ""])


__all__ = ["Database", "ResumePoint", "RunPoint", "make_engine", "SQLITE_SYNCHRONOUS", "insert_ignore", "retry_collisions",
           "plain_url", "BATCH_ACTIVE_STATES", "BATCH_END_STATES", "RUN_ACTIVE_STATES", "RUN_END_STATES"]
