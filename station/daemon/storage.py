"""Where the daemon's records go, and whether they got there.

One storage path for every station: a configured database URL, or (none given: unit tests, a quick
demo) a SQLite file in a temporary folder, removed when the database is disposed. Both run the same
`db` code (migrations, writer, repository), so a test without a database exercises the storage and
its failures exactly as a production station does.

`Storage` forwards every event of the bus to the database writer (db/writer.py, a thread), turns
its failures into operator alarms, and tells the run's end whether everything of a batch was
committed before the batch may be called finished.
"""

from __future__ import annotations

import asyncio
import logging
import tempfile
from pathlib import Path

from contracts.events import Alarm, EventBus
from contracts.types import StationError
from db.database import Database
from db.writer import DbWriter

log = logging.getLogger(__name__)

EPHEMERAL_URLS = (None, "", "memory://")


def open_database(url: str | None, station: str = "") -> Database:
    """The station's database upgraded to head. No URL (or 'memory://'): a temporary SQLite file,
    deleted with the database. A bad path, an unwritable file or a server that is down is a
    StationError in one line."""
    tmp: tempfile.TemporaryDirectory | None = None
    if url in EPHEMERAL_URLS:
        tmp = tempfile.TemporaryDirectory(prefix="station-db-")
        url = f"sqlite:///{Path(tmp.name) / 'station.db'}"
    assert url is not None
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
        raise StationError(f"database {url}: {type(reason).__name__}: {reason}".rstrip()) from None
    if tmp is not None:
        database.temporary_dir = tmp  # lives (and is removed) with the database object
    return database


def storage_state(writer: DbWriter | None) -> str:
    """'ok', or 'error: ...' while the writer cannot store (what /api/health reports)."""
    if writer is not None and writer.failing is not None:
        return f"error: writes failing: {writer.failing} ({writer.backlog} events waiting)"
    return "ok"


class Storage:
    """The bus -> database writer link of one daemon (started and stopped with the station)."""

    def __init__(self, db: Database, bus: EventBus) -> None:
        self.db = db
        self.bus = bus
        self.writer: DbWriter | None = None
        self._queue: asyncio.Queue | None = None
        self._task: asyncio.Task | None = None

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.writer = DbWriter(self.db, on_storage=lambda reason: loop.call_soon_threadsafe(self._alarm, reason))
        q = self.bus.subscribe(maxsize=100000, drop=False)

        async def forward() -> None:
            while True:
                ev = await q.get()
                try:
                    self.writer.submit(ev)  # type: ignore[union-attr]
                except Exception:
                    log.exception("db writer refused %s", type(ev).__name__)

        self._queue = q
        self._task = loop.create_task(forward(), name="db-forward")

    async def stop(self) -> None:
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
        """Wait until everything of the batch so far is committed. None if stored, else why not."""
        w = self.writer
        if w is None:
            return None
        q = self._queue
        for _ in range(int(timeout_s / 0.01)):
            if q is None or q.empty() or w.failing is not None:
                break
            await asyncio.sleep(0.01)
        if w.failing is None and await asyncio.to_thread(w.flush, timeout_s):
            return None
        return w.failing or f"database writes did not complete within {timeout_s:g} s"

    async def flush(self) -> None:
        """Wait until every event published so far is committed (tests, --once summary)."""
        if self.writer is None:
            return
        await self._drained()
        await asyncio.to_thread(self.writer.flush)
