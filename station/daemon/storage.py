"""Where the daemon's records go, and whether they got there.

One storage path for every station: a configured database URL, or (none given: unit tests, a quick
demo) a SQLite file in a temporary folder, removed when the database is disposed. Both run the same
`db` code (migrations, writer, repository), so a test without a database exercises the storage and
its failures exactly as a production station does.

`Storage` forwards every event of the bus to the database writer (db/writer.py, a thread), turns
its failures into operator alarms, and tells the run's end whether everything of a batch was
stored before the batch may be called finished: committed, or in the station's journal
(db/journal.py) waiting to be forwarded. The journal is what lets a station test through a
database outage: a PostgreSQL restart, a hung server, a SQLite file locked by another process.

`DbProbe` asks the database a trivial question every second on its own thread, so /api/health and
the page can say "database not answering since 12 s" without ever waiting on the database
themselves, and the routes that read the database answer 503 at once instead of piling up behind a
hung server. For a SQLite file it also watches the file itself (db/file_guard.py): deleted,
replaced or moved under the daemon raises the storage alarm, stops new batches, rescues what the
deleted file held and sends every later event to the journal.
"""

from __future__ import annotations

import asyncio
import logging
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

from sqlalchemy import text

from contracts.events import Alarm, Event, EventBus
from contracts.types import StationError
from db.database import Database, plain_url
from db.file_guard import StoreFile
from db.models import SCHEMA_REVISION
from db.journal import Journal, journal_path_for
from db.writer import DbWriter

log = logging.getLogger(__name__)

EPHEMERAL_URLS = (None, "", "memory://")


def open_database(url: str | None, station: str = "", *, allow_new: bool = False,
                  journal_path: str | None = None, forward: bool = True) -> Database:
    """The station's database upgraded to head, with what the station's journal held forwarded into
    it first (db/journal.py: events of an earlier run the database did not take then; forwarded
    BEFORE the restart bookkeeping marks runs interrupted, so a batch that ended during an outage
    keeps its own end and verdicts). No URL (or 'memory://'): a temporary SQLite file, deleted with
    the database. A bad path, an unwritable file or a server that is down is a StationError in one
    line.

    A SQLite file is checked against its marker (db/file_guard.py): a database that held batches
    and is now missing, empty or holds fewer is refused in one line (restore it, or allow_new:
    `--new-database`), never silently replaced by a new one: an MES holding `since=N` would skip
    the first new results, histories and attempts would start again. forward=False (`serve --check`,
    which writes nothing) leaves the journal for the station's next real start."""
    tmp: tempfile.TemporaryDirectory[str] | None = None
    if url in EPHEMERAL_URLS:
        tmp = tempfile.TemporaryDirectory(prefix="station-db-")
        url = f"sqlite:///{Path(tmp.name) / 'station.db'}"
    assert url is not None
    guard = StoreFile.of_url(url) if tmp is None else None
    if guard is not None:
        guard.check_before_open(allow_new)
    try:
        if url.startswith("sqlite:///"):
            path = Path(url[len("sqlite:///"):])
            if str(path) not in ("", ":memory:"):
                path.parent.mkdir(parents=True, exist_ok=True)
        database = Database(url, station=station)
        database.upgrade()
    except StationError:
        raise
    except Exception as exc:  # noqa: BLE001 - one line for the operator, whatever the driver raised
        reason = getattr(exc, "orig", None) or exc
        raise StationError(f"database {plain_url(url)}: {type(reason).__name__}: {reason}".rstrip()) from None
    if tmp is not None:
        database.temporary_dir = tmp  # lives (and is removed) with the database object
    if guard is not None:
        guard.opened()
        n, top = database.batch_counts()
        guard.check_at_open(n, top, allow_new, schema=SCHEMA_REVISION)
        database.file_guard = guard
    jpath = journal_path or journal_path_for(url, station)
    if jpath is not None and tmp is None and forward:
        forward_journal(database, jpath)
    return database


def set_aside_stale_wal(path: Path) -> list[Path]:
    """After the database file was deleted or replaced under the station: its -wal and -shm left
    at the path belong to the old file (their content is in the rescued copy), and SQLite would
    replay that WAL into whatever file is put at the path (a WAL does not name its database).
    They are renamed aside (`station.db-wal.stale-<UTC>`), never deleted."""
    from datetime import datetime, timezone

    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    moved = []
    for suffix in ("-wal", "-shm"):
        p = path.with_name(path.name + suffix)
        if p.exists():
            target = p.with_name(f"{p.name}.stale-{stamp}")
            try:
                p.rename(target)
                moved.append(target)
            except OSError:
                log.exception("storage: %s could not be set aside", p)
    if moved:
        log.warning("storage: the old database's %s set aside (its content is in the rescued copy)",
                    ", ".join(m.name for m in moved))
    return moved


def forward_journal(db: Database, path: Path | str, timeout_s: float = 300.0) -> int:
    """Forward what an earlier run of the station left in its journal (the database was down when
    it stopped). Returns how many events were forwarded; a database that will not take them is a
    StationError (starting on it would judge as interrupted runs whose end waits in the journal)."""
    p = Path(path).expanduser()
    if not p.exists():
        return 0
    journal = Journal(p)
    try:
        n = journal.pending
        if not n:
            return 0
        log.warning("storage: forwarding %d events the station's journal %s holds from an earlier run", n, p)
        writer = DbWriter(db, journal=journal)
        writer.flush(timeout_s)
        writer.close(bound_s=timeout_s)
        if journal.pending:
            raise StationError(f"the station's journal {p} holds {journal.pending} events the database "
                               f"{plain_url(str(db.url))} does not take ({writer.failing or 'no answer'}): "
                               "the station starts once they are stored")
        log.warning("storage: %d journaled events stored", n)
        return n
    finally:
        journal.close()


PROBE_INTERVAL_S = 1.0
NOT_ANSWERING_AFTER_S = 2.0  # a probe in progress this long: the database is "not answering"


class DbProbe:
    """Is the database answering? One thread asks `SELECT 1` every PROBE_INTERVAL_S (and, for a
    SQLite file, checks the file is still the one opened); `problem()` reads the answer without
    touching the database, so health and the routes never wait on a hung server."""

    def __init__(self, db: Database, on_file_problem: Callable[[str], None] | None = None,
                 interval_s: float = PROBE_INTERVAL_S) -> None:
        self.db = db
        self.interval_s = interval_s
        self.on_file_problem = on_file_problem
        self.last_ok = time.time()
        self.asking_since: float | None = None  # time.time() of the probe in progress
        self.error: str | None = None
        self.error_since: float | None = None
        self.file_problem: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="db-probe", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def problem(self, now: float | None = None) -> str | None:
        """One sentence while the database is not usable, else None."""
        now = time.time() if now is None else now
        if self.file_problem is not None:
            return self.file_problem
        if self.asking_since is not None and now - self.asking_since >= NOT_ANSWERING_AFTER_S:
            return f"database not answering since {now - self.last_ok:.0f} s"
        if self.error is not None:
            return f"database unreachable since {now - (self.error_since or now):.0f} s: {self.error}"
        return None

    def _loop(self) -> None:
        guard = getattr(self.db, "file_guard", None)
        while not self._stop.is_set():
            if guard is not None and self.file_problem is None:
                why = guard.problem()
                if why is not None:
                    self.file_problem = why
                    log.critical("%s", why)
                    if self.on_file_problem is not None:
                        try:
                            self.on_file_problem(why)
                        except Exception:  # noqa: BLE001 - the alarm is raised either way
                            log.exception("storage: handling the database file problem failed")
            if self.file_problem is not None:  # a new connection would create an empty file at the path
                self._stop.wait(self.interval_s)
                continue
            self.asking_since = time.time()
            try:
                with self.db.engine.connect() as conn:
                    conn.execute(text("SELECT 1"))
                self.last_ok = time.time()
                self.error = self.error_since = None
            except Exception as exc:  # noqa: BLE001 - any driver's error is "unreachable"
                reason = str(getattr(exc, "orig", None) or exc).strip().splitlines()
                if self.error is None:
                    self.error_since = time.time()
                self.error = (reason[0] if reason else type(exc).__name__)[:200]
            finally:
                self.asking_since = None
            self._stop.wait(self.interval_s)


def storage_state(writer: DbWriter | None, probe: DbProbe | None = None) -> str:
    """'ok', 'forwarding: ...' while journaled events go to a database that answers again, or
    'error: ...' while the database cannot be used (what /api/health reports)."""
    problem = probe.problem() if probe is not None else None
    waiting = writer.waiting if writer is not None else 0
    tail = f"; {waiting} events wait in the station's journal" if waiting else ""
    if problem is not None:
        return f"error: {problem}{tail}"
    if writer is not None and writer.failing is not None:
        return f"error: writes failing: {writer.failing} ({writer.backlog} events queued{tail})"
    if waiting:
        return f"forwarding: {waiting} events from the station's journal to the database"
    return "ok"


class Storage:
    """The bus -> database writer link of one daemon (started and stopped with the station)."""

    def __init__(self, db: Database, bus: EventBus, journal_path: str | None = None) -> None:
        self.db = db
        self.bus = bus
        self.journal_path = journal_path  # config `journal_path`; None: beside the database (journal_path_for)
        self.journal: Journal | None = None
        self.probe: DbProbe | None = None
        self.writer: DbWriter | None = None
        self._queue: asyncio.Queue[Event] | None = None
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        path = self.journal_path or journal_path_for(str(self.db.url), getattr(self.db, "station", ""))
        self.journal = Journal(path) if path is not None else None
        if self.journal is not None and self.journal.pending:
            log.warning("storage: %d events of an earlier run wait in the journal %s: forwarded to the database "
                        "now", self.journal.pending, self.journal.path)
        def on_storage(reason: str | None) -> None:  # the writer's thread: the alarm is raised in the loop
            loop.call_soon_threadsafe(self._alarm, reason)

        self.writer = DbWriter(self.db, journal=self.journal, on_storage=on_storage)
        writer = self.writer
        self.probe = DbProbe(self.db, on_file_problem=lambda why: self._file_problem(why, loop))
        self.probe.start()
        q = self.bus.subscribe(maxsize=100000, drop=False)

        async def forward() -> None:
            while True:
                ev = await q.get()
                try:
                    writer.submit(ev)
                except Exception:
                    log.exception("db writer refused %s", type(ev).__name__)

        self._queue = q
        self._task = loop.create_task(forward(), name="db-forward")

    def blocked(self) -> str | None:
        """Why no new batch may start now (the database file gone or a database that does not
        answer), else None. Running batches go on: their events are journaled."""
        return self.probe.problem() if self.probe is not None else None

    def waiting(self) -> dict[str, object]:
        """What waits to be forwarded: {"events": n, "batches": {batch_id: n}} (the page's banner)."""
        if self.journal is None or not self.journal.pending:
            return {"events": 0, "batches": {}}
        return {"events": self.journal.pending, "batches": self.journal.batches()}

    def _file_problem(self, why: str, loop: asyncio.AbstractEventLoop) -> None:
        """On the probe's thread: the database file was deleted, replaced or moved. Nothing more
        goes into it (the writer journals), and what the deleted file held is copied out."""
        w = self.writer
        if w is not None:
            w.block(why)
            for _ in range(100):  # a commit in progress into the old file: let it end first
                if w._commit_started is None:
                    break
                time.sleep(0.05)
        guard = getattr(self.db, "file_guard", None)
        rescued = None
        if guard is not None:
            try:
                rescued = guard.rescue()
            except Exception:  # noqa: BLE001 - the alarm still goes out
                log.exception("storage: the deleted database file could not be rescued")
        # Close the connections to the old file: SQLite then checkpoints into it and removes its
        # -wal and -shm, which a later connection at the path would otherwise replay into whatever
        # file is there now (a WAL belongs to one database file). Nothing opens a new connection
        # here any more: the writer journals, the probe stops asking, batches and reads are refused.
        try:
            self.db.engine.dispose()
        except Exception:  # noqa: BLE001
            log.exception("storage: closing the old database file's connections failed")
        if guard is not None:
            set_aside_stale_wal(guard.path)
        text_ = (f"{why}. New batches are refused; running batches go on and their records wait in the station's "
                 f"journal. " + (f"What the file held is saved as {rescued}: put it back (or restore a backup) and "
                                 "restart the station." if rescued is not None else
                                 "Restore the file from a backup and restart the station."))
        loop.call_soon_threadsafe(self.bus.publish, Alarm(0, text=text_, severity="critical"))

    async def stop(self) -> None:
        if self.probe is not None:
            self.probe.stop()
        if self._task is not None:
            q = self._queue
            assert q is not None
            while not q.empty():  # hand over what is still queued
                try:
                    self.writer.submit(q.get_nowait())  # type: ignore[union-attr]
                except Exception:
                    break
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
            self.bus.unsubscribe(q)
            self._task = None
        if self.writer is not None:
            try:
                await asyncio.to_thread(self.writer.close)
            except Exception:
                log.exception("closing db writer")
            self.writer = None

    def _alarm(self, reason: str | None) -> None:
        """The writer's storage failed (reason) or recovered (None): tell the operator at once."""
        if reason is not None:
            text = (f"database write failing: {reason}. Results are held in memory and retried; "
                    "free disk space / check the database. A batch ending now is not reported finished.")
            self.bus.publish(Alarm(0, text=text, severity="critical"))
        else:
            self.bus.publish(Alarm(0, text="database writes work again: held results stored", severity="info"))

    async def _drained(self) -> None:
        q = self._queue
        while q is not None and not q.empty():
            await asyncio.sleep(0.01)

    async def stored_before_end(self, timeout_s: float = 15.0) -> str | None:
        """Wait until everything of the batch so far is durable (committed, or in the journal).
        None if stored, else why not (the journal's own disk failing too: a full disk)."""
        w = self.writer
        if w is None:
            return None
        q = self._queue
        for _ in range(int(timeout_s / 0.01)):
            if q is None or q.empty() or (w.failing is not None and w.journal is None):
                break
            await asyncio.sleep(0.01)
        if w.journal is not None:  # durable = committed or journaled: the database may be down
            if await asyncio.to_thread(w.flush, timeout_s):
                return None
            return w.failing or f"database writes did not complete within {timeout_s:g} s"
        if w.failing is None and await asyncio.to_thread(w.flush, timeout_s):
            return None
        return w.failing or f"database writes did not complete within {timeout_s:g} s"

    async def flush(self) -> None:
        """Wait until every event published so far is committed (tests, --once summary)."""
        if self.writer is None:
            return
        await self._drained()
        await asyncio.to_thread(self.writer.flush)
