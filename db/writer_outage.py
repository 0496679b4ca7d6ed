"""The writer's side for when storage fails or hangs: journal, forward, stall watchdog, lost answers.

Why a module of its own: db/writer.py is the writer's normal path (queue, batch, commit); this is
everything it does when that path does not work, which is most of its subtlety.

With a journal (db/journal.py, the station's own durable file; the daemon always gives one), a
storage failure no longer holds events in memory: the events of the failed commit and every event
after them go to the journal at once (durable), and the writer forwards the journal to the database,
oldest first, whenever it takes writes again. `flush()` then means "durable": committed, or in the
journal. A commit that hangs (a PostgreSQL server that stopped answering) cannot be interrupted
without risking a commit the database makes after the station gave up, so it is left to finish; the
watchdog copies its events and everything queued behind it into the journal meanwhile (a copy the
writer removes once the hung commit goes through). Without a journal, or when the journal's own disk
fails too, the writer holds events in memory and retries.

A commit that hangs (SQLite file locked by another process, a slow disk: the commit blocks inside
SQLite's busy timeout) is a storage failure too: a watchdog reports it through `on_storage` once a
commit has been in progress for `stall_s`, sets `failing`, and reports the recovery when the commit
goes through.

A commit whose answer is lost (the connection cut while COMMIT was on its way) may have happened:
every writer transaction first stores a token (db.models.WriterCommit), and the database is asked
for it before the events are stored again, so nothing is stored twice.

`WriterOutage` is a base class of db.writer.DbWriter: the attributes annotated below that it does
not set in `_init_outage` are DbWriter's.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
from collections.abc import Callable
from typing import TypedDict

from sqlalchemy import select
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.exc import OperationalError

from contracts.events import Event
from db.database import Database
from db.event_store import EventStore
from db.journal import Journal
from db.models import WriterCommit

log = logging.getLogger("db.writer")  # the writer's log, whichever of its modules speaks

FORWARD_CHUNK = 500  # journaled events forwarded per transaction

Entry = tuple[int, Event]  # an event and its sequence number (its order; the journal's key)


class WriterStats(TypedDict):
    """DbWriter.stats: counters since the writer started, and the last error in words."""

    submitted: int
    committed_events: int
    committed_samples: int
    commits: int
    dropped_events: int
    unbound_events: int
    last_error: str
    storage_failures: int
    abandoned_events: int
    stalls: int
    journaled_events: int
    forwarded_events: int
    lost_answers: int


def _reason(exc: Exception) -> str:
    """A storage error in the operator's words: the driver's own message."""
    return str(getattr(exc, "orig", exc)).strip() or type(exc).__name__


class _OutcomeUnknown(Exception):
    """A commit failed in a way that may have committed, the database cannot say now, and its
    entries are in the journal under its token (DbWriter._settle_lost_answer)."""


class _Marker:
    """A flush (done once everything before it is durable) or, with stop, the writer's end."""

    def __init__(self, stop: bool = False) -> None:
        self.done = threading.Event()
        self.stop = stop


class WriterOutage:
    """Journal, forward, stall watchdog and commit tokens of DbWriter (see the module docstring)."""

    # DbWriter's, used here
    db: Database
    stats: WriterStats
    max_events: int
    _q: queue.SimpleQueue[Entry | _Marker]
    _abandon: threading.Event
    _thread: threading.Thread
    _events: EventStore

    def _init_outage(self, journal: Journal | None, on_storage: Callable[[str | None], None] | None,
                     retry_max_s: float, stall_s: float) -> None:
        self.journal = journal
        self._journal_lock = threading.RLock()  # the writer thread and the watchdog both journal
        # what the writer thread holds now (taken off the queue, not yet committed): its entries and
        # the flush markers behind them; the watchdog copies them into the journal while a commit
        # hangs (then those markers are done: durable), and a commit that goes through afterwards
        # takes its copies out again (_copied: their sequence numbers)
        self._holding: list[Entry] = []
        # the commit in progress: its token (db.models.WriterCommit) and entries; the sqlite3
        # connection it runs on (interrupted when close() gives up on it: it must not commit later)
        self._inflight: tuple[str, list[Entry]] | None = None
        self._inflight_dbapi: DBAPIConnection | None = None
        self._holding_markers: list[_Marker] = []
        self._copied: set[int] = set()
        self._next_forward = 0.0  # time.monotonic() of the next try to forward the journal
        self._forward_failures = 0
        self.blocked: str | None = None  # why the database must not be written now (its file deleted)
        self.on_storage = on_storage
        self.retry_max_s = retry_max_s
        self.failing: str | None = None  # why storage fails now (None = healthy)
        self.failing_since: float | None = None
        self.stall_s = float(stall_s)
        self._failing_lock = threading.RLock()  # the writer thread and the stall watchdog both report
        self._commit_started: float | None = None  # time.monotonic() of the commit in progress
        self._stalled = False  # the watchdog reported the commit in progress as stalled
        self.stall_latency_s: float | None = None  # commit start -> stall alarm, last time it fired

    def _commit(self, events: list[Event], seal_all: bool, token: str | None = None) -> None:
        raise NotImplementedError  # DbWriter._commit: one transaction

    def _interrupt_inflight(self) -> None:
        """A SQLite commit close() gave up on (it waits on another process's lock) is interrupted:
        left alone it could commit after its events were journaled, and be stored twice. A server
        database's hung commit cannot be interrupted safely (the server may have it): its token
        decides at the next forward."""
        conn = self._inflight_dbapi
        if conn is not None and self.db.is_sqlite:
            try:
                getattr(conn, "interrupt")()  # sqlite3.Connection.interrupt
            except Exception:  # noqa: BLE001 - the connection closed meanwhile: nothing to stop
                pass

    def block(self, reason: str) -> None:
        """Write nothing more to this database (its file was deleted or replaced under the
        station): from now on every event goes to the journal, kept for the database restored."""
        self.blocked = reason
        self._set_failing(reason)
        self._spill()

    def _to_journal(self, entries: list[Entry], token: str | None = None) -> bool:
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
                if not self._forward_commit(chunk):
                    return False
            except Exception:  # noqa: BLE001 - a bad event among them: one by one, the rest stored
                log.exception("db writer: forwarding %d journaled events failed; one by one", len(chunk))
                for one in chunk:
                    try:
                        if not self._forward_commit([one]):
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

    def _forward_commit(self, entries: list[Entry]) -> bool:
        """Commit journaled entries. False, after a backoff, when the database failed or the
        commit's answer was lost (the whole forward waits); a bad event's error propagates."""
        try:
            self._commit_timed(entries, False)
        except _OutcomeUnknown:
            self._backoff(self.stats["last_error"] or "a commit's answer was lost")
            return False
        except OperationalError as exc:
            self._backoff(_reason(exc))
            return False
        return True

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
                self._events.chunks.bufs.clear()
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

    def _commit_timed(self, entries: list[Entry], seal_all: bool) -> None:
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

    def _done_with_copies(self, entries: list[Entry]) -> None:
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

    def _settle_lost_answer(self, token: str, entries: list[Entry]) -> bool:
        """After a failed commit: True when it did commit after all (its token is there); its
        sample chunks are then read back from the database (this process's bookkeeping was rolled
        back with the error). False when it did not. When it cannot be told now (the database is
        away), the entries are journaled with the token and _OutcomeUnknown is raised: the forward
        asks again before it stores them, so they are never stored twice."""
        verdict = self._committed(token)
        if verdict:
            self.stats["lost_answers"] += 1
            self._events.chunks.bufs.clear()  # re-read each run's chunks: the commit stored them
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


__all__ = ["WriterOutage", "WriterStats", "Entry", "FORWARD_CHUNK"]
