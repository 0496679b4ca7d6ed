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

Why this module is only the thread: what a transaction contains is db/event_store.py (which rows,
the MES record's numbering, the outbox option) with the row shapes in db/event_rows.py and the MES
key and counter in db/mes_record.py; what the writer does when storage fails or hangs (the
journal, the stall watchdog, commits whose answer was lost) is db/writer_outage.py. The names
callers import from here (DbWriter, CommitInfo, record_key, take_result_seq, the row helpers, the
constants) stay importable from here.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from collections.abc import Callable
from datetime import timedelta

from sqlalchemy import delete, insert
from sqlalchemy.exc import OperationalError

from contracts.events import Event
from contracts.json_safe import plain_json
from db.database import Database
from db.event_rows import VERDICT_FIELDS, sfem_rows, thermal_rows, verdict_columns
from db.event_store import AUDIT_VERDICT_SUPERSEDED, CommitInfo, EventStore
from db.journal import Journal
from db.mes_record import mes_key, take_result_seq
from db.models import WriterCommit, utcnow
from db.writer_outage import FORWARD_CHUNK, Entry, WriterOutage, WriterStats, _Marker, _OutcomeUnknown, _reason

log = logging.getLogger(__name__)

TOKEN_KEEP = timedelta(days=1)  # writer_commit rows older than this are removed (every TOKEN_PRUNE_EVERY commits)
TOKEN_PRUNE_EVERY = 1000
CLOSE_BOUND_S = 5.0  # close() with a journal: what is not committed by then waits in the journal
STALL_ALARM_S = 5.0  # a commit in progress longer than this raises the storage alarm (DbWriter(stall_s=))

record_key = mes_key  # the writer's name for the MES idempotency key (web/db_repo.py imports it)


class DbWriter(WriterOutage):
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
        self._init_outage(journal, on_storage, retry_max_s, stall_s)  # db/writer_outage.py
        self._seq = journal.max_seq if journal is not None else 0  # the events' order (the journal's key)
        self.station = str(getattr(database, "station", "") or "")  # stamped on every result row
        self._abandon = threading.Event()
        self._held: list[Entry] = []  # the events of the commit being retried
        self.interval_s = interval_s
        self.max_events = max_events
        self.seal_samples = seal_samples
        self.outbox = outbox
        self.on_commit = on_commit
        self._q: queue.SimpleQueue[Entry | _Marker] = queue.SimpleQueue()
        # what a transaction contains (db/event_store.py): runs bound, sample chunks, verdict records
        self._events = EventStore(database, self.station, seal_samples, outbox, on_unbound=self._count_unbound)
        self._closed = False
        self.stats: WriterStats = {
            "submitted": 0, "committed_events": 0, "committed_samples": 0, "commits": 0,
            "dropped_events": 0, "unbound_events": 0, "last_error": "", "storage_failures": 0,
            "abandoned_events": 0, "stalls": 0, "journaled_events": 0, "forwarded_events": 0, "lost_answers": 0,
        }
        self._thread = threading.Thread(target=self._loop, name="db-writer", daemon=True)
        self._thread.start()
        self._watchdog = threading.Thread(target=self._watch_stalls, name="db-writer-watchdog", daemon=True)
        self._watchdog.start()

    def _count_unbound(self) -> None:
        self.stats["unbound_events"] += 1

    # ---- called from the event loop (cheap, non-blocking) -----------------------------------
    def bind_run(self, batch_id: int, slot: str, run_id: int) -> None:
        """Events of (batch_id, slot) belong to run_id (from Database.create_run)."""
        self._events.bind_run(batch_id, slot, run_id)

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

    def __exit__(self, *exc: object) -> None:
        self.close()

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

    def _store(self, entries: list[Entry], seal_all: bool) -> None:
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

    def _commit_storage_retry(self, entries: list[Entry], seal_all: bool) -> bool:
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

    def _commit_with_retry(self, entries: list[Entry], seal_all: bool = False) -> None:
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
        saved = self._events.chunks.snapshot()
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
                self._events.apply(conn, events, seal_all, info)  # db/event_store.py
        except BaseException:
            self._events.chunks.restore(saved)
            raise
        self.stats["commits"] += 1
        self.stats["committed_events"] += len(events)
        self.stats["committed_samples"] += info.n_samples
        if self.on_commit is not None:
            try:
                self.on_commit(info)
            except Exception:
                log.exception("db writer: on_commit callback failed")


__all__ = ["DbWriter", "CommitInfo", "thermal_rows", "sfem_rows", "plain_json", "verdict_columns", "VERDICT_FIELDS", "take_result_seq",
           "record_key", "STALL_ALARM_S", "CLOSE_BOUND_S", "FORWARD_CHUNK", "AUDIT_VERDICT_SUPERSEDED"]
