"""Engine, sessions, migrations and the daemon's synchronous bookkeeping calls.

SQLite by default (one file, WAL, foreign keys on), any SQLAlchemy URL otherwise: the same code runs
on PostgreSQL. Bulk data (samples, segments, results) goes through db.writer.DbWriter off the event
loop; the calls here are the few small writes the daemon needs an id back from.

SQLite durability: journal_mode=WAL with synchronous=FULL. WAL alone already survives a killed
process (a commit is in the WAL file before COMMIT returns); FULL adds an fsync of the WAL on every
commit, so an acknowledged commit also survives a power cut or kernel panic, which a factory station
must expect. The cost is one fsync per writer transaction, and the writer batches ~0.2 s of events
per transaction, so it is a handful of fsyncs per second.
"""

from __future__ import annotations

import logging
import random
import sqlite3
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from sqlalchemy import create_engine, event, func, select, update
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from contracts.trace import Trace
from contracts.types import StationError
from db.models import NO_ATTEMPT, SCHEMA_REVISION, Batch, Dut, DutRun, MeasuredBy, SampleChunk, SegmentRow, utcnow

log = logging.getLogger(__name__)

DB_DIR = Path(__file__).resolve().parent
ALEMBIC_INI = DB_DIR / "alembic.ini"
MIGRATIONS_DIR = DB_DIR / "migrations"

BATCH_ACTIVE_STATES = ("created", "running", "paused")
BATCH_END_STATES = ("finished", "aborted", "failed", "interrupted")
RUN_ACTIVE_STATES = ("connecting", "identified", "running")
RUN_END_STATES = ("done", "faulted", "interrupted")
SQLITE_SYNCHRONOUS = "FULL"


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


def _sqlite_on_connect(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute(f"PRAGMA synchronous={SQLITE_SYNCHRONOUS}")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def _sqlite_read_only_on_connect(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA query_only=ON")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def plain_url(url: str) -> str:
    """A database URL without its password, for messages and stored records; a string that is not
    a URL is shown as given."""
    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - not a URL: shown as given
        return url


def make_read_only_engine(url: str) -> Engine:
    """An engine that cannot change the database: SQLite opened with mode=ro (a file that does not
    exist is an error, never created; no WAL switch, no migration), PostgreSQL in read-only
    transactions."""
    u = make_url(url)
    if u.get_backend_name() == "sqlite":
        path = u.database or ""
        if path in ("", ":memory:") or not Path(path).expanduser().is_file():
            raise StationError(f"database {url}: no such file (a source database is never created)")
        uri = "file:" + str(Path(path).expanduser().resolve()) + "?mode=ro"
        engine = create_engine("sqlite://", creator=lambda: sqlite3.connect(uri, uri=True, timeout=30,
                                                                            check_same_thread=False))
        event.listen(engine, "connect", _sqlite_read_only_on_connect)
        return engine
    return create_engine(u, pool_pre_ping=True,
                         connect_args={"options": "-c default_transaction_read_only=on"})


def make_engine(url: str, **kwargs: Any) -> Engine:
    """An engine for `url`; SQLite gets WAL, synchronous=FULL, foreign keys, a busy timeout."""
    u = make_url(url)
    if u.get_backend_name() == "sqlite":
        if u.database and u.database != ":memory:" and not u.database.startswith("file:"):
            Path(u.database).expanduser().parent.mkdir(parents=True, exist_ok=True)
        kwargs.setdefault("connect_args", {}).setdefault("timeout", 30)
        engine = create_engine(u, **kwargs)
        event.listen(engine, "connect", _sqlite_on_connect)
        return engine
    kwargs.setdefault("pool_pre_ping", True)
    kwargs.setdefault("pool_timeout", PG_POOL_TIMEOUT_S)
    if u.get_backend_name() == "postgresql" and u.get_driver_name() in ("psycopg", "psycopg2"):
        args = kwargs.setdefault("connect_args", {})
        for k, v in PG_CONNECT_ARGS.items():
            args.setdefault(k, v)
    return create_engine(u, **kwargs)


# PostgreSQL: nothing the station asks may wait for ever (issue 37). A server that is down is met
# in connect_timeout; a statement or a lock that takes too long is ended by the server; a
# connection whose peer vanished (a network cut, a host that died) is found by TCP keepalives and
# tcp_user_timeout. A server that is alive but stopped (SIGSTOP, a hung host) answers none of these:
# the station's DbProbe (station/daemon/storage.py) says so, the routes fail fast, and the writer's
# watchdog journals what waits behind a hung commit.
PG_POOL_TIMEOUT_S = 5.0
PG_CONNECT_ARGS: dict[str, Any] = {
    "connect_timeout": 5,
    "options": "-c statement_timeout=60000 -c lock_timeout=30000 -c idle_in_transaction_session_timeout=120000",
    "keepalives": 1,
    "keepalives_idle": 10,
    "keepalives_interval": 5,
    "keepalives_count": 3,
    "tcp_user_timeout": 30000,
}

COLLISION_RETRIES = 5  # a unique collision or a serialization failure is retried this many times
RETRY_PGCODES = ("40001", "40P01")  # PostgreSQL serialization_failure, deadlock_detected


def insert_ignore(bind: Any, model: Any, conflict_columns: list[str]) -> Any:
    """INSERT ... ON CONFLICT (conflict_columns) DO NOTHING for the bind's dialect (SQLite and
    PostgreSQL): the database decides who inserts the row; the loser's insert does nothing and
    waits for the winner's commit on PostgreSQL, so the row can be read right after."""
    name = bind.get_bind().dialect.name if hasattr(bind, "get_bind") else bind.dialect.name
    if name == "postgresql":
        from sqlalchemy.dialects.postgresql import insert as dialect_insert
    elif name == "sqlite":
        from sqlalchemy.dialects.sqlite import insert as dialect_insert
    else:
        raise StationError(f"insert-or-get is not implemented for {name} databases (SQLite, PostgreSQL)")
    return dialect_insert(model).on_conflict_do_nothing(index_elements=conflict_columns)


def _retryable(exc: Exception) -> bool:
    if isinstance(exc, IntegrityError):
        return "unique" in str(exc.orig).lower() or "duplicate" in str(exc.orig).lower()
    if isinstance(exc, OperationalError):
        return getattr(exc.orig, "sqlstate", None) in RETRY_PGCODES or getattr(exc.orig, "pgcode", None) in RETRY_PGCODES
    return False


def retry_collisions(fn: Any, what: str, attempts: int = COLLISION_RETRIES,
                     on_retry: Any = None) -> Any:
    """fn() again (its transaction rolled back) after a unique collision or a PostgreSQL
    serialization failure/deadlock, up to `attempts` times: concurrent stations never crash a
    batch on a race the database settles. Other errors, and the last collision, are raised.
    on_retry() is called before each retry (a count: insert-or-get should leave it at 0)."""
    for attempt in range(1, attempts + 1):
        try:
            return fn()
        except (IntegrityError, OperationalError) as exc:
            if attempt == attempts or not _retryable(exc):
                raise
            if on_retry is not None:
                on_retry()
            log.warning("%s: %s, retrying (%d/%d)", what, str(exc.orig).splitlines()[0], attempt, attempts - 1)
            time.sleep(0.01 * attempt * (1 + random.random()))
    raise AssertionError("unreachable")


class Database:
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
        self.file_guard: Any = None

    @property
    def is_sqlite(self) -> bool:
        return self.engine.dialect.name == "sqlite"

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

    # ---- schema ---------------------------------------------------------------------------
    def _alembic_config(self, connection: Any = None) -> Any:
        from alembic.config import Config

        cfg = Config(str(ALEMBIC_INI))
        cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
        url = self.url if self.read_only else self.engine.url.render_as_string(hide_password=False)
        cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
        if connection is not None:
            cfg.attributes["connection"] = connection
        return cfg

    def known_revisions(self) -> set[str]:
        from alembic.script import ScriptDirectory

        script = ScriptDirectory.from_config(self._alembic_config())
        return {rev.revision for rev in script.walk_revisions()}

    def head_revision(self) -> str:
        from alembic.script import ScriptDirectory

        return ScriptDirectory.from_config(self._alembic_config()).get_current_head() or ""

    def current_revision(self) -> str | None:
        """The database's Alembic revision, None for an empty (never migrated) database."""
        from alembic.runtime.migration import MigrationContext

        try:
            with self.engine.connect() as conn:
                return MigrationContext.configure(conn).get_current_revision()
        except OperationalError as exc:
            raise StationError(f"cannot open database {self.url}: {exc.orig}") from None

    def _refuse_unknown(self, rev: str | None) -> None:
        if rev is not None and rev not in self.known_revisions():
            raise StationError(
                f"database {self.engine.url.render_as_string(hide_password=True)} has schema revision "
                f"{rev!r}, newer than (unknown to) this station software, which knows up to "
                f"{self.head_revision()!r}: upgrade the software or point it at another database"
            )

    def integrity(self) -> str:
        """'ok', or what SQLite's quick_check found (PostgreSQL checks itself: always 'ok')."""
        if not self.is_sqlite:
            return "ok"
        from sqlalchemy import text
        from sqlalchemy.exc import DatabaseError

        try:
            with self.engine.connect() as conn:
                rows = [str(r[0]) for r in conn.execute(text("PRAGMA quick_check(5)"))]
        except OperationalError as exc:  # a directory, no permission: not a corruption
            raise StationError(f"cannot open database {self.url}: {exc.orig}") from None
        except DatabaseError as exc:  # "file is not a database", "database disk image is malformed"
            return str(getattr(exc, "orig", exc))
        return "ok" if rows == ["ok"] else "; ".join(rows)

    def check_integrity(self) -> None:
        """Refuse a corrupted database at start, in one line (it once passed `serve --check` and
        then answered 500 on most read routes)."""
        found = self.integrity()
        if found != "ok":
            raise StationError(f"database {self.url} is corrupted ({found[:200]}): restore it from a "
                               "backup or move it away to start with a new one")

    def upgrade(self) -> str:
        """Migrate to the newest schema this code knows; refuse a database from newer code."""
        from alembic import command

        if self.read_only:
            raise StationError(f"database {self.url} is opened read-only: it is never migrated")

        self.check_integrity()
        self._refuse_unknown(self.current_revision())
        with self.engine.begin() as conn:
            command.upgrade(self._alembic_config(conn), "head")
        rev = self.current_revision() or ""
        log.info("database %s at schema revision %s", self, rev)
        return rev

    def check(self) -> str:
        """Refuse an unknown (newer) or outdated schema without changing anything."""
        rev = self.current_revision()
        self._refuse_unknown(rev)
        head = self.head_revision()
        if rev != head:
            raise StationError(
                f"database schema revision {rev!r} is older than this software's {head!r}: "
                "run `station db upgrade`"
            )
        return rev

    # ---- batches and runs (the daemon's synchronous calls) ---------------------------------
    def create_batch(self, profile: str, operator: str, config_snapshot: dict, state: str = "created",
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
        values: dict[str, Any] = {"state": state}
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
                raise KeyError(f"no batch {batch_id}")

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
        values: dict[str, Any] = {"last_seen": now}
        if sensor:
            values["sensor"] = sensor
        s.execute(update(Dut).where(Dut.serial == serial).values(**values).execution_options(synchronize_session=False))
        return s.scalars(select(Dut).where(Dut.serial == serial).execution_options(populate_existing=True)).one()

    def create_run(
        self, batch_id: int, slot: str, serial: str, sensor: str = "", identity: dict | None = None,
        state: str = "identified", *, counts_as_attempt: bool = True, measured_by: MeasuredBy | None = None,
    ) -> int:
        """A new run of `serial` in (batch_id, slot), numbered as the serial's next attempt. Safe with
        several stations on one database: the DUT row is insert-or-get and row-locked while the
        attempt is counted (attempts of real batches are 1..N without duplicates or gaps), and a
        unique collision or a PostgreSQL serialization failure/deadlock is retried.

        counts_as_attempt=False: a run that never tested the part (the label scanned for the slot
        is not the board's serial: station/daemon/slots.py stops it before any data). It is stored
        with attempt 0 (NO_ATTEMPT) so the MES and the history see which board was there, and it
        is no attempt of `serial`: never counted in its attempt numbers, attempts or yields.
        measured_by: the software, firmware and holder that measure the run (None: not known)."""
        return retry_collisions(lambda: self._create_run(batch_id, slot, serial, sensor, identity, state,
                                                         counts_as_attempt, measured_by or MeasuredBy()),
                                f"create run of {serial}", on_retry=self._count_retry)

    def _count_retry(self) -> None:
        self.collision_retries += 1

    def _create_run(self, batch_id: int, slot: str, serial: str, sensor: str, identity: dict | None,
                    state: str, counts_as_attempt: bool = True, measured_by: MeasuredBy = MeasuredBy()) -> int:
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
                         attempt=attempt, label_serial=labels.get(slot) or None, **measured_by.columns())
            s.add(run)
            s.flush()
            return run.id

    def run_attempt(self, run_id: int) -> int:
        """The attempt number of a run (1 = first test of its serial)."""
        with self.session() as s:
            a = s.scalar(select(DutRun.attempt).where(DutRun.id == run_id))
            if a is None:
                raise KeyError(f"no run {run_id}")
            return int(a)

    def set_run_state(self, run_id: int, state: str, fault_reason: str = "") -> None:
        values: dict[str, Any] = {"state": state, "fault_reason": fault_reason}
        if state in RUN_END_STATES:
            values["ended_at"] = utcnow()
        with self.session() as s:
            res = s.execute(update(DutRun).where(DutRun.id == run_id).values(**values))
            if res.rowcount == 0:
                raise KeyError(f"no run {run_id}")

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
                raise KeyError(f"no batch {batch_id}")
            return Trace.of(b)

    def resume_point(self, batch_id: int) -> ResumePoint:
        """What the daemon needs to resume a batch: its last completed step and its runs."""
        with self.session() as s:
            b = s.get(Batch, batch_id)
            if b is None:
                raise KeyError(f"no batch {batch_id}")
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

    def _mine(self, model: Any) -> Any:
        """Rows of this station; rows from before migration 0005 (station '') count as anyone's,
        so a single station upgraded in place still resumes its old batch."""
        return model.station.in_([self.station, ""])

    def sqlite_integrity_check(self) -> str:
        """`PRAGMA integrity_check` ('ok' when sound); 'n/a' on other databases."""
        if not self.is_sqlite:
            return "n/a"
        with self.engine.connect() as conn:
            return str(conn.exec_driver_sql("PRAGMA integrity_check").scalar())


__all__ = ["Database", "ResumePoint", "RunPoint", "make_engine", "SQLITE_SYNCHRONOUS", "insert_ignore", "retry_collisions"]
