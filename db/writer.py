"""DbWriter: the daemon's events into the database, on one thread, off the event loop.

`submit(event)` only puts the event on a queue (never blocks, never touches the database). The
writer thread takes whatever has arrived within `interval_s` (or up to `max_events`) and commits it
in one transaction, so the cost of a commit (an fsync with SQLite synchronous=FULL) is shared by
many events; segments and results are therefore durable a fraction of a second after they happen,
not at batch end. `flush()` returns once everything submitted before it is committed.

Samples: every transaction appends each run's new samples as one small chunk (durable at once);
once a run has `seal_samples` samples in small chunks, the writer replaces them, in the same
transaction, by one sealed chunk, which compresses far better. A crash at any point leaves either
the small chunks or the sealed one, never both and never neither. After a restart the writer picks
up a run's unsealed chunks and goes on compacting them (db/sample_chunks.py).

Storage failures (disk full, an I/O error, a read-only file, a lost PostgreSQL connection) drop
nothing: the writer keeps the events and retries with backoff for as long as it takes, reports the
failure at once through `on_storage` (the daemon raises a critical alarm, health says so, and a
batch whose results are not stored cannot end 'finished'), and reports the recovery. Only an event
the database refuses for itself (a constraint, a bad value) is dropped, counted and logged.

The MES record is the run's FINAL verdict (design 8, docs/verdicts.md): only a DutVerdict takes a
result_seq, the MES cursor of repository.results_since, from a row-locked counter so that its order
is the commit order even with several stations (and writers) on one database (take_result_seq).
Results (DutResult: thermal/SFEM) and program-and-verify records (DutProgrammed, DutVerified) are
stored as data only: no result_seq, no MES message. A DutVerdict for a run that already has a
result_seq (a resumed batch judged again, a re-judge) is a new record that supersedes the old one:
a new result_seq, the run's verdict columns replaced, and an audit entry. Every DutVerdict writes
its row in verdict_history (the feed pages over it: every record reaches the MES once). A replay's
verdict (batch.replay_of) is stored without a result_seq: it never reaches the MES.

With outbox=True the writer also puts the verdict record's MES message in the outbox table in the
same transaction; off by default because the web's MES worker copies results_since into the outbox
itself (two copies would reach the MES under two keys).

With a journal (db/journal.py, the station's own durable file; the daemon always gives one), a
storage failure no longer holds events in memory: the events of the failed commit and every event
after them go to the journal at once (durable), and the writer forwards the journal to the database,
oldest first, whenever it takes writes again. `flush()` then means "durable": committed, or in the
journal. A commit that hangs (a PostgreSQL server that stopped answering) cannot be interrupted
without risking a commit the database makes after the station gave up, so it is left to finish; the
watchdog copies its events and everything queued behind it into the journal meanwhile (a copy the
writer removes once the hung commit goes through). Without a journal, or when the journal's own disk
fails too, the writer holds events in memory and retries as before.

A commit that hangs (SQLite file locked by another process, a slow disk: the commit blocks inside
SQLite's busy timeout) is a storage failure too: a watchdog reports it through `on_storage` once a
commit has been in progress for `stall_s` (default STALL_ALARM_S), sets `failing`, and reports the
recovery when the commit goes through.
"""

from __future__ import annotations

import asyncio
import logging
import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any, Callable

from datetime import timedelta

from sqlalchemy import delete, func, insert, select, update
from sqlalchemy.engine import Connection
from sqlalchemy.exc import OperationalError

from db.journal import Journal
from db.sample_chunks import SampleChunks
from contracts.json_safe import finite_or_none as _num, plain_json
from contracts.sfem_result import SfemResult
from db.database import BATCH_END_STATES, RUN_END_STATES, Database
from db.models import (
    Batch,
    DutRun,
    Outbox,
    ProgramVerifyRow,
    ResultCounter,
    SegmentRow,
    SfemResultRow,
    ThermalResultRow,
    VerdictHistoryRow,
    WriterCommit,
    utcnow,
)
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
from contracts.types import AXES

log = logging.getLogger(__name__)

TOKEN_KEEP = timedelta(days=1)  # writer_commit rows older than this are removed (every TOKEN_PRUNE_EVERY commits)
TOKEN_PRUNE_EVERY = 1000
CLOSE_BOUND_S = 5.0  # close() with a journal: what is not committed by then waits in the journal
FORWARD_CHUNK = 500  # journaled events forwarded per transaction
STALL_ALARM_S = 5.0  # a commit in progress longer than this raises the storage alarm (DbWriter(stall_s=))
AUDIT_VERDICT_SUPERSEDED = "verdict superseded"  # the audit action of a verdict record replaced by a newer one


def thermal_rows(thermal: dict | None) -> list[dict]:
    """Rows for thermal_result from a DutResult.thermal dict: either the `station calibrate --json`
    shape ({"streaming": {...}, "offline": {...}}) or one ThermalResult.to_json()."""
    if not thermal:
        return []
    found: list[tuple[str, dict]] = []
    for key in ("streaming", "offline"):
        v = thermal.get(key)
        if isinstance(v, dict) and isinstance(v.get("axes"), dict):
            found.append((str(v.get("method") or key), v))
    if not found and isinstance(thermal.get("axes"), dict):
        found.append((str(thermal.get("method") or "streaming"), thermal))
    rows = []
    for method, res in found:
        row: dict[str, Any] = {"method": method[:16], "n_segments": int(res.get("n_segments") or 0)}
        for ax in AXES:
            a = res["axes"].get(ax) or {}
            row[f"tdb_{ax}_mg_per_c"] = _num(a.get("tdb_mg_per_c"))
            row[f"tdsf_{ax}_ppm_per_c"] = _num(a.get("tdsf_ppm_per_c"))
            row[f"tdb_sigma_{ax}_mg_per_c"] = _num(a.get("tdb_sigma_mg_per_c"))
            row[f"tdsf_sigma_{ax}_ppm_per_c"] = _num(a.get("tdsf_sigma_ppm_per_c"))
            row[f"tdsf_clamped_{ax}"] = bool(a.get("tdsf_clamped", False))
        row["detail"] = plain_json(res)
        rows.append(row)
    return rows


def sfem_rows(sfem: dict | None) -> list[dict]:
    """Rows for sfem_result from the SFEM record (contracts/sfem_result.py SfemResult, the one
    shape the daemon and `station sfem --json` give): one row per temperature step (its fit) and
    one row for the record (temperature_step None: the reference step's headline figures, the
    record's own keys and, in polynomial_coefficients, the thermal model). db/repository.py
    sfem_json puts them back together. Any other shape raises ValueError (the event is refused)."""
    if not sfem:
        return []
    rec = SfemResult.from_json(sfem)
    rows = [
        {
            "temperature_step": st.temperature_step,
            "temp_c": st.temp_c,
            "rmse_before_mg": st.rmse_before_mg,
            "rmse_after_mg": st.rmse_after_mg,
            "parameters": st.to_json(),
            "polynomial_coefficients": None,
        }
        for st in rec.steps
    ]
    ref = rec.reference
    rows.append(
        {
            "temperature_step": None,
            "temp_c": ref.temp_c,
            "rmse_before_mg": ref.rmse_before_mg,
            "rmse_after_mg": ref.rmse_after_mg,
            "parameters": rec.record_row_json(),
            "polynomial_coefficients": None if rec.thermal is None else plain_json(rec.thermal),
        }
    )
    return rows


VERDICT_FIELDS = ("verdict", "grade", "tray", "reason", "attempt", "limits_name", "limits_version")


def verdict_columns(verdict: dict) -> dict:
    """dut_run columns of a verdict dict (station/decisions/moment.py)."""
    return {
        "verdict": str(verdict.get("verdict") or "")[:16] or None,
        "grade": None if verdict.get("grade") is None else str(verdict["grade"])[:16],
        "tray": None if verdict.get("tray") is None else str(verdict["tray"])[:64],
        "verdict_reason": str(verdict.get("reason") or ""),
        "verdict_detail": plain_json(verdict),
        "limits_name": None if verdict.get("limits_name") is None else str(verdict["limits_name"])[:64],
        "limits_version": None if verdict.get("limits_version") is None else str(verdict["limits_version"])[:32],
    }


def record_key(run_id: int, result_seq: int) -> str:
    """The MES idempotency key of one verdict record (feed, webhook and outbox alike)."""
    return f"result:{run_id}:{result_seq}"


def take_result_seq(conn: Connection) -> int:
    """The next MES cursor value, from the one-row counter (db.models.ResultCounter). The UPDATE
    holds the row lock until this transaction commits, so two writers (two stations on one
    PostgreSQL) take numbers in commit order: `results since N` cannot see N+2 before N+1 exists.
    On SQLite the UPDATE takes the database write lock, which gives the same. Call it late in the
    transaction: the lock is held from here to the commit."""
    value = conn.execute(
        update(ResultCounter).where(ResultCounter.id == 1).values(value=ResultCounter.value + 1)
        .returning(ResultCounter.value)
    ).scalar()
    if value is None:  # the row is made by migration 0005; a hand-made schema may lack it
        start = int(conn.execute(select(func.coalesce(func.max(DutRun.result_seq), 0))).scalar_one()) + 1
        conn.execute(insert(ResultCounter).values(id=1, value=start))
        value = start
    return int(value)


_STORED = (SamplesReceived, SegmentLogged, DutResult, DutVerdict, SlotStateChanged, BatchStateChanged, StepStarted,
           StepCompleted, DutProgrammed, DutVerified)
_BATCH_LEVEL = (BatchStateChanged, StepStarted, StepCompleted)


@dataclass
class CommitInfo:
    """What one writer transaction made durable (passed to `on_commit`)."""

    n_events: int
    n_samples: int
    segments: list[tuple[int, int, int]]  # (run_id, segment index, row id)
    results: list[tuple[int, int]]  # (run_id, result_seq)


def _reason(exc: Exception) -> str:
    """A storage error in the operator's words: the driver's own message."""
    return str(getattr(exc, "orig", exc)).strip() or type(exc).__name__


class _OutcomeUnknown(Exception):
    """A commit failed in a way that may have committed, the database cannot say now, and its
    entries are in the journal under its token (DbWriter._settle_lost_answer)."""


class _Marker:
    def __init__(self, stop: bool = False) -> None:
        self.done = threading.Event()
        self.stop = stop


class DbWriter:
    """One writer thread: `submit()` events, `flush()` to wait for their commit, `close()`."""

    def __init__(
        self,
        database: Database,
        interval_s: float = 0.2,
        max_events: int = 2000,
        seal_samples: int = 1024,
        outbox: bool = False,
        on_commit: Callable[[CommitInfo], None] | None = None,
        on_storage: Callable[[str | None], None] | None = None,
        retry_max_s: float = 5.0,
        stall_s: float = STALL_ALARM_S,
        journal: Journal | None = None,
    ) -> None:
        self.db = database
        self.journal = journal
        self._seq = journal.max_seq if journal is not None else 0  # the events' order (the journal's key)
        self._journal_lock = threading.RLock()  # the writer thread and the watchdog both journal
        # what the writer thread holds now (taken off the queue, not yet committed): its entries and
        # the flush markers behind them; the watchdog copies them into the journal while a commit
        # hangs (then those markers are done: durable), and a commit that goes through afterwards
        # takes its copies out again (_copied: their sequence numbers)
        self._holding: list[tuple[int, Event]] = []
        # the commit in progress: its token (db.models.WriterCommit) and entries; the sqlite3
        # connection it runs on (interrupted when close() gives up on it: it must not commit later)
        self._inflight: tuple[str, list[tuple[int, Event]]] | None = None
        self._inflight_dbapi: Any = None
        self._holding_markers: list[_Marker] = []
        self._copied: set[int] = set()
        self._next_forward = 0.0  # time.monotonic() of the next try to forward the journal
        self._forward_failures = 0
        self.blocked: str | None = None  # why the database must not be written now (its file deleted)
        self.station = str(getattr(database, "station", "") or "")  # stamped on every result row
        self.on_storage = on_storage
        self.retry_max_s = retry_max_s
        self.failing: str | None = None  # why storage fails now (None = healthy)
        self.failing_since: float | None = None
        self.stall_s = float(stall_s)
        self._failing_lock = threading.RLock()  # the writer thread and the stall watchdog both report
        self._commit_started: float | None = None  # time.monotonic() of the commit in progress
        self._stalled = False  # the watchdog reported the commit in progress as stalled
        self.stall_latency_s: float | None = None  # commit start -> stall alarm, last time it fired
        self._abandon = threading.Event()
        self._held: list = []  # the events of the commit being retried
        self.interval_s = interval_s
        self.max_events = max_events
        self.seal_samples = seal_samples
        self.outbox = outbox
        self.on_commit = on_commit
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._runs: dict[tuple[int, str], int] = {}
        self._replay: dict[int, bool] = {}  # batch id -> is a replay (its results get no result_seq)
        self._runs_lock = threading.Lock()
        self._chunks = SampleChunks(seal_samples)  # db/sample_chunks.py
        self._closed = False
        self.stats: dict[str, Any] = {
            "submitted": 0, "committed_events": 0, "committed_samples": 0, "commits": 0,
            "dropped_events": 0, "unbound_events": 0, "last_error": "", "storage_failures": 0,
            "abandoned_events": 0, "stalls": 0, "journaled_events": 0, "forwarded_events": 0, "lost_answers": 0,
        }
        self._thread = threading.Thread(target=self._loop, name="db-writer", daemon=True)
        self._thread.start()
        self._watchdog = threading.Thread(target=self._watch_stalls, name="db-writer-watchdog", daemon=True)
        self._watchdog.start()

    # ---- called from the event loop (cheap, non-blocking) -----------------------------------
    def bind_run(self, batch_id: int, slot: str, run_id: int) -> None:
        """Events of (batch_id, slot) belong to run_id (from Database.create_run)."""
        with self._runs_lock:
            self._runs[(batch_id, slot)] = run_id

    def submit(self, event: Event) -> None:
        if self._closed:
            raise RuntimeError("DbWriter is closed")
        self.stats["submitted"] += 1
        self._seq += 1
        self._q.put((self._seq, event))

    @property
    def backlog(self) -> int:
        return self._q.qsize()

    @property
    def waiting(self) -> int:
        """Events waiting to be forwarded from the journal to the database."""
        return self.journal.pending if self.journal is not None else 0

    def flush(self, timeout: float | None = None) -> bool:
        """Block until everything submitted so far is durable (True) or timeout (False): committed,
        or (with a journal) in the journal waiting to be forwarded."""
        if not self._thread.is_alive():
            return self._q.empty()
        m = _Marker()
        self._q.put(m)
        return m.done.wait(timeout)

    async def aflush(self, timeout: float | None = None) -> bool:
        return await asyncio.to_thread(self.flush, timeout)

    def close(self, timeout: float | None = 60.0, bound_s: float | None = None) -> None:
        """Commit everything, seal every run's pending samples, stop the thread.

        With a journal, close is bounded (`bound_s`, default CLOSE_BOUND_S; a SIGTERM must end in
        seconds, docs/design.md): what the database has not taken by then is put in the journal
        (forwarded at the next start) and the writer thread, if a commit still hangs, is left
        behind (a daemon thread: the process may exit)."""
        if self._closed:
            return
        self._closed = True
        m = _Marker(stop=True)
        self._q.put(m)
        if self.journal is not None:
            bound = CLOSE_BOUND_S if bound_s is None else bound_s
            if self.failing is not None or self._stalled:
                self._spill()  # storage is down: durable now, the writer's last try only forwards
            if m.done.wait(bound if timeout is None else min(timeout, bound)):
                self._thread.join(1.0)
                return
            self._abandon.set()
            self._spill()
            self._interrupt_inflight()
            n = self.journal.pending
            log.critical("db writer: the database did not finish within %.1f s at shutdown: %d events wait in the "
                         "journal %s (forwarded at the next start)", bound, n, self.journal.path)
            self._thread.join(0.5)
            return
        if self.failing is not None and not self._stalled and timeout is not None:
            # storage is down: one more try, then say what is lost (a stall, a lock held by another
            # process, gets the whole timeout: it usually passes)
            timeout = min(timeout, 5.0)
        if not m.done.wait(timeout):
            self._abandon.set()
        self._thread.join(timeout)

    def __enter__(self) -> "DbWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _interrupt_inflight(self) -> None:
        """A SQLite commit close() gave up on (it waits on another process's lock) is interrupted:
        left alone it could commit after its events were journaled, and be stored twice. A server
        database's hung commit cannot be interrupted safely (the server may have it): its token
        decides at the next forward."""
        conn = self._inflight_dbapi
        if conn is not None and self.db.is_sqlite:
            try:
                conn.interrupt()
            except Exception:  # noqa: BLE001 - the connection closed meanwhile: nothing to stop
                pass

    # ---- the journal (db/journal.py) -----------------------------------------------------------
    def block(self, reason: str) -> None:
        """Write nothing more to this database (its file was deleted or replaced under the
        station): from now on every event goes to the journal, kept for the database restored."""
        self.blocked = reason
        self._set_failing(reason)
        self._spill()

    def _to_journal(self, entries: list[tuple[int, Event]], token: str | None = None) -> bool:
        """Put entries in the journal (durable on return); token: the transaction they were in
        when its answer was lost. False if the journal cannot take them either (its disk is full
        too): the caller holds them in memory as before."""
        if self.journal is None:
            return False
        if not entries:
            return True
        with self._journal_lock:
            try:
                added = self.journal.append(entries, token)
            except Exception as exc:  # noqa: BLE001 - disk full, I/O error: memory is what is left
                self.stats["last_error"] = f"journal: {exc}"
                log.error("db writer: the journal %s does not take events either (%s): held in memory",
                          self.journal.path, exc)
                return False
        self.stats["journaled_events"] += added
        return True

    def _spill(self) -> None:
        """From any thread: copy the hung commit's entries and move everything queued behind it into
        the journal; flush markers behind them are done (durable), a stop marker goes back."""
        if self.journal is None:
            return
        with self._journal_lock:
            if self._inflight is not None:  # the hung commit: its outcome is its token's
                token, inflight = self._inflight
                fresh = [e for e in inflight if e[0] not in self._copied]
                if fresh and self._to_journal(fresh, token):
                    self._copied.update(s for s, _ in fresh)
            holding = [e for e in self._holding if e[0] not in self._copied]
            if holding and self._to_journal(holding):
                self._copied.update(s for s, _ in holding)
            if not [e for e in self._holding if e[0] not in self._copied]:
                for m in self._holding_markers:  # everything before them is durable now
                    m.done.set()
            items = []
            while True:
                try:
                    items.append(self._q.get_nowait())
                except queue.Empty:
                    break
            entries = [i for i in items if not isinstance(i, _Marker)]
            if not self._to_journal(entries):
                for i in items:  # the journal failed: back in order, for the writer
                    self._q.put(i)
                return
            for i in items:
                if isinstance(i, _Marker):
                    if i.stop:
                        self._q.put(i)
                    else:
                        i.done.set()

    def _forward_journal(self, everything: bool = False) -> bool:
        """Forward the journal to the database, oldest first, in transactions of FORWARD_CHUNK
        events. True once the journal is empty; False when the database failed again (the next
        try is after a backoff)."""
        assert self.journal is not None
        if self.blocked is not None:
            self._set_failing(self.blocked)
            return False
        while self.journal.pending and not self._abandon.is_set():
            chunk = self.journal.oldest(FORWARD_CHUNK)
            if not chunk:
                break
            settled = self._settle_tokens([s for s, _ in chunk])
            if settled is None:
                self._backoff("no answer to the commit tokens' question")
                return False
            if settled:
                chunk = [e for e in chunk if e[0] not in settled]
                if not chunk:
                    continue
            try:
                self._commit_timed(chunk, False)
            except _OutcomeUnknown:
                self._backoff(self.stats["last_error"] or "a commit's answer was lost")
                return False
            except OperationalError as exc:
                self._backoff(_reason(exc))
                return False
            except Exception:  # noqa: BLE001 - a bad event among them: one by one, the rest stored
                log.exception("db writer: forwarding %d journaled events failed; one by one", len(chunk))
                for one in chunk:
                    try:
                        self._commit_timed([one], False)
                    except _OutcomeUnknown:
                        self._backoff(self.stats["last_error"] or "a commit's answer was lost")
                        return False
                    except OperationalError as exc:
                        self._backoff(_reason(exc))
                        return False
                    except Exception as exc:  # noqa: BLE001
                        self.stats["dropped_events"] += 1
                        self.stats["last_error"] = repr(exc)
                        log.error("db writer: dropped journaled %s: %r", type(one[1]).__name__, exc)
                        self.journal.remove([one[0]])
            self.journal.remove([s for s, _ in chunk])
            self.stats["forwarded_events"] += len(chunk)
            self._forward_failures = 0
            self._set_failing(None)
            if not everything and self._q.qsize() > self.max_events:
                break  # new events keep their pace: they go behind the journal, forwarded next
        return not self.journal.pending

    def _settle_tokens(self, seqs: list[int]) -> set[int] | None:
        """Journal entries held under a token (a commit whose answer was lost): those whose commit
        did happen are removed from the journal, not stored again (their seqs are returned); those
        whose commit did not are plain entries again. None: the database cannot tell now."""
        assert self.journal is not None
        done: set[int] = set()
        for token, tseqs in self.journal.tokens(seqs).items():
            verdict = self._committed(token)
            if verdict is None:
                return None
            if verdict:
                self.journal.remove(tseqs)
                done.update(tseqs)
                self._chunks.bufs.clear()
                self.stats["lost_answers"] += 1
                log.warning("db writer: %d journaled events were committed by a commit whose answer was lost: "
                            "not stored again", len(tseqs))
            else:
                self.journal.set_token(tseqs, None)
        return done

    def _backoff(self, reason: str) -> None:
        """The forward failed (why): try again after a growing pause (at most retry_max_s)."""
        self.stats["last_error"] = reason
        self.stats["storage_failures"] += 1
        self._forward_failures += 1
        self._next_forward = time.monotonic() + min(self.retry_max_s, 0.25 * 2 ** min(self._forward_failures, 6))
        self._set_failing(reason)

    # ---- writer thread ----------------------------------------------------------------------
    def _loop(self) -> None:
        while True:
            if self.journal is not None and self.journal.pending and time.monotonic() >= self._next_forward \
                    and not self._abandon.is_set():
                self._forward_journal()
            wait = None
            if self.journal is not None and self.journal.pending:
                wait = max(0.05, self._next_forward - time.monotonic())
            try:
                first = self._q.get(timeout=wait)
            except queue.Empty:
                continue
            items = [first]
            if not isinstance(first, _Marker):
                deadline = time.monotonic() + self.interval_s
                while len(items) < self.max_events:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    try:
                        item = self._q.get(timeout=remaining)
                    except queue.Empty:
                        break
                    items.append(item)
                    if isinstance(item, _Marker):
                        break
            entries = [i for i in items if not isinstance(i, _Marker)]
            markers = [i for i in items if isinstance(i, _Marker)]
            stop = any(m.stop for m in markers)
            with self._journal_lock:
                self._holding, self._holding_markers = entries, [m for m in markers if not m.stop]
            if entries or stop:
                self._store(entries, seal_all=stop)
            with self._journal_lock:
                self._holding, self._holding_markers = [], []
            for m in markers:
                m.done.set()
            if stop:
                return

    def _store(self, entries: list[tuple[int, Event]], seal_all: bool) -> None:
        """Commit entries, or (older events waiting in the journal) put them behind those."""
        if self.journal is not None and self.journal.pending and self._to_journal(entries):
            if seal_all and not self._abandon.is_set() and self._forward_journal(everything=True):
                self._seal_all()
            return
        self._commit_with_retry(entries, seal_all=seal_all)

    def _seal_all(self) -> None:
        try:
            self._commit([], True)
        except Exception as exc:  # noqa: BLE001 - sealing is compaction: the next start goes on with it
            self.stats["last_error"] = repr(exc)
            log.error("db writer: final sealing failed: %r", exc)

    # ---- stall watchdog ---------------------------------------------------------------------
    def _watch_stalls(self) -> None:
        """Report a commit in progress for longer than stall_s as a storage failure. The commit
        itself cannot say so: it blocks inside SQLite's busy timeout (another process holds the
        lock), in a slow fsync or on a server that stopped answering, so only another thread can
        see the time pass. While it hangs, events are journaled here (_spill)."""
        tick_s = max(0.02, min(0.1, self.stall_s / 20))
        while self._thread.is_alive():
            started = self._commit_started
            if started is not None and not self._stalled:
                waited_s = time.monotonic() - started
                if waited_s >= self.stall_s:
                    self._report_stall(waited_s)
            if self._stalled and self._commit_started is not None:
                self._spill()
            time.sleep(tick_s)

    def _report_stall(self, waited_s: float) -> None:
        """Under the lock, so a commit that ends meanwhile reports its recovery after this."""
        with self._failing_lock:
            if self._commit_started is None or self._stalled:
                return  # the commit finished meanwhile
            self._stalled = True
            self.stall_latency_s = waited_s
            self.stats["stalls"] += 1
            self._set_failing(f"stalled: a commit has been waiting {waited_s:.1f} s (database locked?)")

    def _commit_timed(self, entries: list[tuple[int, Event]], seal_all: bool) -> None:
        """_commit under a new token, watched by the stall watchdog while it runs. A commit whose
        answer is lost (an OperationalError: the connection cut while COMMIT was on its way) may
        have happened: the database is asked for its token (`_settle_lost_answer`) before the
        events are stored again. A commit that went through after the watchdog copied its entries
        into the journal takes the copies out again."""
        token = uuid.uuid4().hex
        with self._journal_lock:
            self._inflight = (token, entries)
        self._commit_started = time.monotonic()
        try:
            self._commit([e for _, e in entries], seal_all, token)
        except OperationalError:
            if self._settle_lost_answer(token, entries):
                return  # it did commit: nothing to store again
            raise
        finally:
            with self._failing_lock:
                self._commit_started = None
            with self._journal_lock:
                self._inflight = None
                self._inflight_dbapi = None
        self._done_with_copies(entries)

    def _done_with_copies(self, entries: list[tuple[int, Event]]) -> None:
        with self._journal_lock:
            done = [s for s, _ in entries if s in self._copied]
            self._copied.difference_update(done)
        if done and self.journal is not None:
            self.journal.remove(done)

    def _committed(self, token: str) -> bool | None:
        """Did the transaction with this token commit? None: the database cannot tell now."""
        try:
            with self.db.engine.connect() as conn:
                return conn.execute(select(WriterCommit.token).where(WriterCommit.token == token)).first() is not None
        except Exception:  # noqa: BLE001 - down, hung, refused: unknown
            return None

    def _settle_lost_answer(self, token: str, entries: list[tuple[int, Event]]) -> bool:
        """After a failed commit: True when it did commit after all (its token is there); its
        sample chunks are then read back from the database (this process's bookkeeping was rolled
        back with the error). False when it did not. When it cannot be told now (the database is
        away), the entries are journaled with the token and _OutcomeUnknown is raised: the forward
        asks again before it stores them, so they are never stored twice."""
        verdict = self._committed(token)
        if verdict:
            self.stats["lost_answers"] += 1
            self._chunks.bufs.clear()  # re-read each run's chunks: the commit stored them
            log.warning("db writer: a commit's answer was lost but it did commit (%d events): not stored again",
                        len(entries))
            self._done_with_copies(entries)
            return True
        if verdict is None and self.journal is not None and self._to_journal(entries, token):
            self.journal.set_token([s for s, _ in entries], token)  # those it held already
            raise _OutcomeUnknown(token)
        return False

    def _set_failing(self, reason: str | None) -> None:
        with self._failing_lock:
            if reason == self.failing:
                return
            if reason is None:
                self._stalled = False
            was = self.failing
            self.failing = reason
            self.failing_since = time.time() if reason is not None else None
        if reason is not None and was is None:
            where = f"journaled in {self.journal.path}" if self.journal is not None else "held in memory"
            log.critical("db writer: the database does not take writes (%s): events %s, retrying", reason, where)
        elif reason is None:
            log.warning("db writer: the database takes writes again; held events stored")
        if self.on_storage is not None:
            try:
                self.on_storage(reason)
            except Exception:
                log.exception("db writer: on_storage callback failed")

    def _commit_storage_retry(self, entries: list[tuple[int, Event]], seal_all: bool) -> bool:
        """Commit, retrying storage failures with backoff until they pass (True), the entries are
        in the journal (True) or close() gives up (False). Raises what is not a storage failure
        (a bad event)."""
        attempt = 0
        self._held = entries
        if self.blocked is not None and self._to_journal(entries):
            self._set_failing(self.blocked)
            return True
        while True:
            try:
                self._commit_timed(entries, seal_all)
                self._set_failing(None)
                return True
            except _OutcomeUnknown:  # journaled under its token: the forward decides
                self._forward_failures = max(self._forward_failures, 1)
                self._next_forward = time.monotonic() + min(self.retry_max_s, 0.5)
                self._set_failing(self.stats["last_error"] or "the database's answer to a commit was lost")
                return True
            except OperationalError as exc:  # disk full, I/O error, locked, lost connection
                reason = _reason(exc)
                self.stats["last_error"] = reason
                self.stats["storage_failures"] += 1
                attempt += 1
                hard = "full" in reason or "I/O" in reason or "readonly" in reason
                if attempt >= 3 or hard or self._abandon.is_set():
                    if self._to_journal(entries):  # durable now; forwarded when the database answers
                        self._forward_failures = max(self._forward_failures, 1)
                        self._next_forward = time.monotonic() + min(self.retry_max_s, 0.5)
                        self._set_failing(reason)
                        return True
                    self._set_failing(reason)
                else:
                    log.warning("db writer: commit failed (%s), retrying", reason)
                if self._abandon.is_set():
                    n = len(entries) + self._q.qsize()
                    self.stats["abandoned_events"] += n
                    log.critical("db writer: giving up at shutdown: %d events NOT stored (%s)", n, reason)
                    return False
                time.sleep(min(self.retry_max_s, 0.2 * attempt))

    def _commit_with_retry(self, entries: list[tuple[int, Event]], seal_all: bool = False) -> None:
        try:
            if self._commit_storage_retry(entries, seal_all) or self._abandon.is_set():
                return
        except Exception as exc:  # a bad event: isolate it, keep the rest
            self.stats["last_error"] = repr(exc)
            log.exception("db writer: commit of %d events failed; retrying one by one", len(entries))
        for entry in entries:
            try:
                if not self._commit_storage_retry([entry], False):
                    return
            except Exception as exc:
                self.stats["dropped_events"] += 1
                self.stats["last_error"] = repr(exc)
                log.error("db writer: dropped %s: %r", type(entry[1]).__name__, exc)
        if seal_all and not (self.journal is not None and self.journal.pending):
            self._seal_all()

    def _commit(self, events: list[Event], seal_all: bool, token: str | None = None) -> None:
        saved = self._chunks.snapshot()
        info = CommitInfo(len(events), 0, [], [])
        try:
            with self.db.engine.begin() as conn:
                with self._journal_lock:
                    self._inflight_dbapi = conn.connection.dbapi_connection
                if token is not None:  # first: the transaction's own proof that it committed
                    conn.execute(insert(WriterCommit).values(token=token, station=self.station[:64],
                                                             committed_at=utcnow()))
                    if self.stats["commits"] % TOKEN_PRUNE_EVERY == 0:
                        conn.execute(delete(WriterCommit).where(WriterCommit.committed_at < utcnow() - TOKEN_KEEP))
                samples: dict[int, list[SamplesReceived]] = {}
                seal: set[int] = set()
                # verdicts take their result_seq last (take_result_seq), so the counter's row lock
                # is held only for the commit, not while samples are compressed
                numbered: list[tuple[int, int, Callable[[Connection, int | None], None]]] = []
                for ev in events:
                    if not isinstance(ev, _STORED):
                        continue  # prompts, lamp, alarms, steps: not stored
                    if isinstance(ev, SlotStateChanged) and not ev.batch_id:
                        continue  # a slot's state between batches (connect, identify): no run to store it in
                    run_id = None if isinstance(ev, _BATCH_LEVEL) else self._run_id(conn, ev)
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
                    info.n_samples += self._chunks.store(conn, samples, seal)
                self._chunks.seal(conn, sorted(seal | (set(self._chunks.bufs) if seal_all else set())))
                for batch_id, run_id, finish in numbered:
                    if self._is_replay(conn, batch_id):  # a replay's verdicts never reach the MES
                        finish(conn, None)
                        continue
                    seq = take_result_seq(conn)
                    finish(conn, seq)
                    info.results.append((run_id, seq))
        except BaseException:
            self._chunks.restore(saved)
            raise
        self.stats["commits"] += 1
        self.stats["committed_events"] += len(events)
        self.stats["committed_samples"] += info.n_samples
        if self.on_commit is not None:
            try:
                self.on_commit(info)
            except Exception:
                log.exception("db writer: on_commit callback failed")

    def _is_replay(self, conn: Connection, batch_id: int) -> bool:
        if batch_id not in self._replay:
            self._replay[batch_id] = conn.execute(
                select(Batch.replay_of).where(Batch.id == batch_id)).scalar() is not None
        return self._replay[batch_id]

    def _run_id(self, conn: Connection, ev: Event) -> int | None:
        slot = getattr(ev, "slot", None)
        key = (ev.batch_id, slot)
        with self._runs_lock:
            run_id = self._runs.get(key)
        if run_id is None:
            run_id = conn.execute(
                select(DutRun.id).where(DutRun.batch_id == ev.batch_id, DutRun.slot == slot).order_by(DutRun.id.desc())
            ).scalars().first()
            if run_id is None:
                self.stats["unbound_events"] += 1
                # a slot's state before its board identified (connecting) has no run yet: expected
                level = logging.DEBUG if isinstance(ev, SlotStateChanged) else logging.WARNING
                log.log(level, "db writer: no run for batch %s slot %s; %s dropped", ev.batch_id, slot, ev.kind)
                return None
            with self._runs_lock:
                self._runs.setdefault(key, run_id)
        return run_id

    def _segment(self, conn: Connection, run_id: int, ev: SegmentLogged) -> int:
        sg = ev.segment
        values = {
            "run_id": run_id,
            "step_index": int(ev.step_index),
            "position": None if sg.position is None else int(sg.position),
            "seg_index": int(sg.index),
            "orientation": int(sg.orientation),
            "n_samples": int(sg.n_samples),
            "temp_mean_c": float(sg.temp_mean_c),
            "temp_std_c": float(sg.temp_std_c),
            "t_start_s": float(sg.t_start_s),
            "t_end_s": float(sg.t_end_s),
            "created_at": utcnow(),
        }
        for k, ax in enumerate(AXES):
            values[f"acc_mean_{ax}_g"] = float(sg.acc_mean_g[k])
            values[f"acc_std_{ax}_g"] = float(sg.acc_std_g[k])
        return int(conn.execute(insert(SegmentRow).values(**values)).inserted_primary_key[0])

    def _result(self, conn: Connection, run_id: int, ev: DutResult) -> None:
        """The analysis' results (thermal, SFEM): data only. No result_seq, no MES message: the
        record the MES gets is the run's final verdict (DutVerdict)."""
        now = utcnow()
        for row in thermal_rows(ev.thermal):
            conn.execute(insert(ThermalResultRow).values(run_id=run_id, station=self.station, created_at=now, **row))
        for row in sfem_rows(ev.sfem):
            conn.execute(insert(SfemResultRow).values(run_id=run_id, station=self.station, created_at=now, **row))

    def _verdict(self, conn: Connection, run_id: int, ev: DutVerdict) -> Callable[[Connection, int | None], None]:
        """The run's final verdict: one MES record. Returns what stores it once its result_seq is
        taken (at the end of the transaction; None for a replay)."""
        now = utcnow()
        return lambda conn, seq: self._store_verdict(conn, run_id, ev, seq, now)

    def _store_verdict(self, conn: Connection, run_id: int, ev: DutVerdict, seq: int | None, now: Any) -> None:
        """The verdict columns of the run, its verdict_history row and, when it replaces a record
        the MES already has a number for, the audit entry of the supersession."""
        verdict = dict(ev.verdict or {})
        old = conn.execute(select(DutRun.result_seq, DutRun.verdict, DutRun.grade, DutRun.tray, DutRun.verdict_reason)
                           .where(DutRun.id == run_id)).first()
        supersedes = old.result_seq if (old is not None and seq is not None) else None
        cols = verdict_columns(verdict)
        values: dict[str, Any] = {**cols, "judged_at": now}
        if seq is not None:
            values["result_seq"] = seq
        conn.execute(update(DutRun).where(DutRun.id == run_id).values(**values))
        conn.execute(insert(VerdictHistoryRow).values(
            run_id=run_id, result_seq=seq, station=self.station, verdict=cols["verdict"], grade=cols["grade"],
            tray=cols["tray"], reason=cols["verdict_reason"], detail=cols["verdict_detail"],
            limits_name=cols["limits_name"], limits_version=cols["limits_version"], judged_at=now,
            supersedes_seq=supersedes))
        if supersedes is not None:
            self._audit_superseded(conn, run_id, ev, old, seq, cols)
        if self.outbox and seq is not None:
            self._outbox_verdict(conn, run_id, ev, seq, supersedes, now)

    def _audit_superseded(self, conn: Connection, run_id: int, ev: DutVerdict, old: Any, seq: int, cols: dict) -> None:
        from db.repository import audit_append

        detail = {
            "run_id": run_id, "serial": ev.serial, "slot": ev.slot, "batch_id": ev.batch_id,
            "old": {"result_seq": old.result_seq, "idempotency_key": record_key(run_id, old.result_seq),
                    "verdict": old.verdict, "grade": old.grade, "tray": old.tray, "reason": old.verdict_reason},
            "new": {"result_seq": seq, "idempotency_key": record_key(run_id, seq), "verdict": cols["verdict"],
                    "grade": cols["grade"], "tray": cols["tray"], "reason": cols["verdict_reason"]},
        }
        audit_append(self.db, "station", AUDIT_VERDICT_SUPERSEDED, f"run {run_id} ({ev.serial or '-'})", detail,
                     station=self.station, conn=conn)

    def _outbox_verdict(self, conn: Connection, run_id: int, ev: DutVerdict, seq: int, supersedes: int | None,
                        now: Any) -> None:
        from db.repository import revision_of

        revision = int(conn.execute(select(revision_of(run_id, seq))).scalar_one())
        payload = {
            "result_seq": seq, "run_id": run_id, "batch_id": ev.batch_id, "slot": ev.slot, "serial": ev.serial,
            "revision": revision, "supersedes": None if supersedes is None else record_key(run_id, supersedes),
            **{k: (ev.verdict or {}).get(k) for k in VERDICT_FIELDS},
        }
        conn.execute(insert(Outbox).values(
            idempotency_key=record_key(run_id, seq), topic="result", payload=payload, attempts=0,
            next_attempt_at=now, last_error="", created_at=now,
        ))

    def _program_verify(self, conn: Connection, run_id: int, ev: DutProgrammed | DutVerified) -> None:
        """Upsert the run's program_verify row: data only (the verdict, at the run's end, is the
        record the MES gets)."""
        now = utcnow()
        row = conn.execute(select(ProgramVerifyRow.id).where(ProgramVerifyRow.run_id == run_id)).scalar()
        if isinstance(ev, DutProgrammed):
            p = plain_json(ev.program)
            values: dict[str, Any] = {
                "programmed": bool(p.get("programmed")), "crc": p.get("crc"), "readback_crc": p.get("readback_crc"),
                "comp_on": bool(p.get("comp")), "attempts": int(p.get("attempts") or 0),
                "error_kind": str(p.get("error_kind") or ""), "error": str(p.get("error") or ""), "program": p,
                "updated_at": now,
            }
        else:
            v = plain_json(ev.verification)
            before, after = v.get("e_before_mg") or {}, v.get("e_after_mg") or {}
            values = {"verified": bool(v.get("passed")), "flags": list(v.get("flags") or []), "verification": v,
                      "updated_at": now}
            for ax in AXES:
                values[f"e_before_{ax}_mg"] = _num(before.get(ax))
                values[f"e_after_{ax}_mg"] = _num(after.get(ax))
        if row is None:
            base = {"programmed": False, "comp_on": False, "attempts": 0, "error_kind": "", "error": "", "flags": [],
                    "program": {}, "created_at": now}
            conn.execute(insert(ProgramVerifyRow).values(run_id=run_id, station=self.station, **{**base, **values}))
        else:
            conn.execute(update(ProgramVerifyRow).where(ProgramVerifyRow.id == row).values(**values))

    def _slot_state(self, conn: Connection, run_id: int, ev: SlotStateChanged) -> None:
        values: dict[str, Any] = {"state": ev.state, "fault_reason": ev.fault_reason}
        values["ended_at"] = utcnow() if ev.state in RUN_END_STATES else None  # None: resumed
        conn.execute(update(DutRun).where(DutRun.id == run_id).values(**values))

    def _step_completed(self, conn: Connection, ev: StepCompleted) -> None:
        """The resume point: committed after (or with) every sample and segment of the step."""
        windows = conn.execute(select(Batch.step_windows).where(Batch.id == ev.batch_id)).scalar()
        windows = dict(windows or {})
        windows[str(ev.step_index)] = {
            slot: [float(a) if math.isfinite(a) else None, float(b) if math.isfinite(b) else None]
            for slot, (a, b) in ev.windows.items()
        }
        conn.execute(
            update(Batch)
            .where(Batch.id == ev.batch_id)
            .values(last_completed_step=ev.step_index, step_windows=windows)
        )

    def _batch_state(self, conn: Connection, ev: BatchStateChanged) -> set[int]:
        values: dict[str, Any] = {"state": ev.state}
        if ev.reason:
            values["reason"] = ev.reason
        values["ended_at"] = utcnow() if ev.state in BATCH_END_STATES else None  # None: resumed
        conn.execute(update(Batch).where(Batch.id == ev.batch_id).values(**values))
        if ev.state not in BATCH_END_STATES:
            return set()
        return set(conn.execute(select(DutRun.id).where(DutRun.batch_id == ev.batch_id)).scalars())


__all__ = ["DbWriter", "CommitInfo", "thermal_rows", "sfem_rows", "plain_json", "verdict_columns", "VERDICT_FIELDS", "take_result_seq",
           "record_key", "STALL_ALARM_S"]
