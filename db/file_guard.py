"""Guards for the station's SQLite file: noticing that it was deleted, replaced or moved
while the daemon uses it, saving what the still-open file holds, and refusing to start silently on
a new empty database after the old one was lost.

Why this exists: on POSIX a deleted file lives on while a process holds it open, so SQLite keeps
reading and writing the unlinked inode. Nothing fails; health says ok, the batch finishes, and the
results vanish when the daemon exits. On the next start SQLAlchemy creates a new empty file, batch
ids restart at 1 and an MES that holds `since=3` silently skips the new results.

Three pieces, all for one file path (`StoreFile`):

- identity: `opened()` records (st_dev, st_ino) once the database is open; `problem()` is one
  os.stat() comparing the path with that identity (cheap enough for a 1 s watchdog).
- rescue: the deleted inode is still reachable through this process's open descriptors
  (/proc/self/fd). `rescue()` copies the database and its -wal out of them into a new file beside
  the path.
- marker: `<path>.marker.json` records how many batches (and the highest batch id) the file held.
  `check_before_open()` (before the engine can create an empty file) and `check_at_open()` (after,
  with counts) refuse a file that is missing, empty or holds less than the marker recorded, unless
  the operator asked for a new database (`--new-database`, `allow_new=True`).

Rescue design choice: the SQLite online backup API cannot be used on the deleted file. SQLite
resolves symlinks in the filename, so `/proc/self/fd/N` becomes "/path/station.db (deleted)":
read-only it fails ("unable to open database file"), read-write it silently CREATES a new empty
file of that name. Even if it opened, SQLite would look for the WAL at "<name>-wal" and lose every
commit not yet checkpointed. So `rescue()` copies bytes: the database and its -wal with os.pread()
on the descriptors SQLite already holds (never opening and closing a new descriptor for the file:
closing any descriptor of a file drops every POSIX lock this process holds on it, SQLite's locks
included). The pair is then opened as an ordinary SQLite database, which replays the WAL, is
checked (PRAGMA quick_check) and checkpointed into one self-contained file (journal_mode=DELETE).
The copy is consistent while the station keeps writing: within one WAL generation a checkpoint only
writes pages into the database that are also in the WAL, and a torn or uncommitted WAL tail is
discarded by the WAL checksums on replay; the WAL header is compared before and after the copy and
the copy is retried if the WAL was restarted (new salts) meanwhile.

Linux-only parts (/proc/self/fd): telling "deleted" from "moved" and `rescue()`. Elsewhere
`problem()` still notices a missing or replaced file and `rescue()` returns None.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sqlite3
import tempfile
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from sqlalchemy.engine import make_url

from contracts.types import StationError

log = logging.getLogger(__name__)

PROC_FD = Path("/proc/self/fd")
DELETED_SUFFIX = " (deleted)"  # what Linux appends to an fd link whose file was unlinked
NEW_DATABASE_FLAG = "--new-database"
_COPY_CHUNK = 1 << 20
_WAL_HEADER_BYTES = 32
_COPY_ATTEMPTS = 3


def _utc_now() -> datetime:
    return datetime.now(timezone.utc).replace(microsecond=0)


def _iso(t: datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


@dataclass(frozen=True)
class Marker:
    """What `<path>.marker.json` recorded about the database the last time the station wrote it."""

    path: str
    created_utc: str
    updated_utc: str
    batches: int
    max_batch_id: int
    schema: str | None = None

    @property
    def had_data(self) -> bool:
        return self.batches > 0 or self.max_batch_id > 0


class StoreFile:
    """One SQLite database file, watched for the life of the daemon.

    Thread-safety: `problem()` may run in a watchdog thread while the event loop calls the rest;
    the only shared mutable state (the cached descriptor number) is behind a lock.
    """

    def __init__(self, path: Path | str) -> None:
        # absolute but not symlink-resolved: the operator's name for the file is what messages show
        # and what os.stat() follows, so re-pointing a symlink also counts as "replaced"
        self.path = Path(path).expanduser().absolute()
        self._identity: tuple[int, int] | None = None
        self._real: str = ""  # realpath at open: SQLite names the WAL after it
        self._fd: int | None = None  # a descriptor of the open database, found in /proc/self/fd
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"StoreFile({str(self.path)!r})"

    @classmethod
    def of_url(cls, url: str) -> StoreFile | None:
        """The file behind a SQLAlchemy URL; None when there is no file to guard (another backend,
        :memory:, a SQLite URI in memory mode, or a string that is not a URL)."""
        try:
            u = make_url(url)
        except Exception:  # noqa: BLE001 - not a URL: nothing to guard
            return None
        if u.get_backend_name() != "sqlite":
            return None
        database = u.database or ""
        if database.startswith("file:"):  # sqlite:///file:path?mode=...&uri=true
            if u.query.get("mode") == "memory" or "mode=memory" in database:
                return None
            database = database[len("file:"):].split("?", 1)[0]
        if database in ("", ":memory:"):
            return None
        return cls(database)

    # -- identity ---------------------------------------------------------------------------------

    def opened(self) -> None:
        """Remember which file the path names now. Call right after the database is opened (and its
        first connection made), so the watchdog compares against the file the station really uses.
        Raises FileNotFoundError if the file does not exist."""
        st = os.stat(self.path)
        with self._lock:
            self._identity = (st.st_dev, st.st_ino)
            self._real = os.path.realpath(self.path)
            self._fd = None
        self._open_fd()  # warm the cache while the name still matches (costs a /proc scan once)

    def problem(self) -> str | None:
        """None while the path still names the file that was opened (or before `opened()`); else one
        sentence for the operator. One os.stat() when all is well; a cached fstat/readlink (or one
        /proc/self/fd scan) only once something is wrong."""
        identity = self._identity
        if identity is None:
            return None
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            st = None
        except OSError as exc:
            return f"the database file {self.path} cannot be checked ({exc.strerror or exc})"
        if st is not None and (st.st_dev, st.st_ino) == identity:
            return None
        where = self._open_location()  # (unlinked, current name) of the file still in use
        if st is None:
            if where is None:
                return (f"the database file {self.path} disappeared (deleted or moved) while the station "
                        f"used it")
            unlinked, name = where
            if unlinked:
                return f"the database file {self.path} was deleted while the station used it"
            return f"the database file {self.path} was moved to {name} while the station used it"
        tail = ""
        if where is not None:
            unlinked, name = where
            tail = " (the one in use was deleted)" if unlinked else f" (the one in use is now {name})"
        return f"the database file {self.path} was replaced by another file while the station used it{tail}"

    # -- rescue -----------------------------------------------------------------------------------

    def rescue(self) -> Path | None:
        """Copy the database the station still holds open to `<name>.rescued-<UTC yyyymmddThhmmss>`
        beside the path and return it, so commits made before (and after) a deletion are not lost
        when the daemon exits. None when there is nothing to rescue: not opened, the path still
        names the open file, or no open descriptor of it is found (all connections closed, or no
        /proc). Costs a full read and write of the database and its WAL plus a quick_check: call it
        once, when `problem()` first reports. Raises StationError if no consistent copy could be made.
        """
        if self._identity is None or self.problem() is None:
            return None
        fd = self._open_fd()
        if fd is None:
            return None
        wal_fd = self._wal_fd(fd)
        parent = self.path.parent
        parent.mkdir(parents=True, exist_ok=True)  # a removed directory is recreated for the copy
        work = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.rescue-", dir=parent))
        try:
            copy = work / "rescued.db"
            self._copy_consistent(fd, wal_fd, copy)
            conn = sqlite3.connect(copy, isolation_level=None)
            try:
                check = conn.execute("PRAGMA quick_check").fetchone()[0]
                if check != "ok":
                    raise StationError(f"rescue of {self.path}: the copied database fails quick_check ({check})")
                # replays the WAL into the file and removes the -wal: one self-contained file
                conn.execute("PRAGMA journal_mode=DELETE")
            finally:
                conn.close()
            with open(copy, "rb+") as f:
                os.fsync(f.fileno())
            target = self._rescue_target()
            os.replace(copy, target)
            _fsync_dir(parent)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        log.warning("%s; its content was copied to %s", self.problem(), target)
        return target

    # -- marker -----------------------------------------------------------------------------------

    @property
    def marker_path(self) -> Path:
        return self.path.with_name(self.path.name + ".marker.json")

    def exists_with_data(self) -> bool:
        """The file exists and is not empty (its WAL counts: a fresh WAL database may hold its
        first commits only there). Two stats."""
        try:
            if self.path.stat().st_size > 0:
                return True
        except FileNotFoundError:
            return False
        wal = self.path.with_name(self.path.name + "-wal")
        try:
            return wal.stat().st_size > 0
        except FileNotFoundError:
            return False

    def read_marker(self) -> Marker | None:
        """The marker, None if there is none. An unreadable marker is a StationError: it was written
        atomically, so a broken one means someone or something else touched the directory."""
        try:
            raw = self.marker_path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        try:
            data = json.loads(raw)
            return Marker(path=str(data["path"]), created_utc=str(data["created_utc"]),
                          updated_utc=str(data["updated_utc"]), batches=int(data["batches"]),
                          max_batch_id=int(data["max_batch_id"]), schema=data.get("schema"))
        except (ValueError, KeyError, TypeError) as exc:
            raise StationError(f"database marker {self.marker_path} is unreadable ({type(exc).__name__}: "
                               f"{exc}); check the database file, then remove the marker or start with "
                               f"{NEW_DATABASE_FLAG}") from None

    def write_marker(self, batches: int, max_batch_id: int, *, schema: str | None = None) -> None:
        """Record what the database holds now. Call after the commit that created (or ended) a batch,
        with counts read from the database: a marker ahead of the file would refuse the next start.
        Atomic (tmp + fsync + rename + directory fsync): two fsyncs, so once per batch, not per
        sample. Keeps the marker's created_utc (and schema when none is given)."""
        try:
            old = self.read_marker()
        except StationError:
            old = None
        self._write_marker(batches, max_batch_id, schema=schema or (old.schema if old else None),
                           created_utc=old.created_utc if old else None)

    def check_before_open(self, allow_new: bool) -> None:
        """Before the engine opens (and so creates) the file: refuse when the marker says a database
        with batches lived here but the file is missing or empty. With allow_new a warning is logged
        and the marker restarted for a new database. No marker: first start, nothing to check.
        Costs a marker read and two stats."""
        marker = self._marker_or_none(allow_new)
        if marker is None or not marker.had_data or self.exists_with_data():
            return
        state = "is missing" if not self.path.exists() else "is empty"
        lost = f"the database file {self.path} {state} but {self._recorded(marker)}"
        if not allow_new:
            raise StationError(f"{lost}; {self._what_to_do()}")
        log.warning("%s; starting a new database as asked (%s)", lost, NEW_DATABASE_FLAG)
        self._write_marker(0, 0, schema=marker.schema, created_utc=None)

    def check_at_open(self, batches_now: int, max_batch_id_now: int, allow_new: bool, *,
                      schema: str | None = None) -> None:
        """After open, with the database's own counts (SELECT count(*), max(id) FROM batch): refuse a
        file that holds fewer batches or a lower highest batch id than the marker recorded (another
        or an older file at the path: batch ids would be reused). With allow_new a warning is logged
        and the marker restarted from the current counts. When it passes the marker records the
        counts (so a database from before markers gets one at its first start)."""
        marker = self._marker_or_none(allow_new)
        fresh = marker is None
        if marker is not None and (batches_now < marker.batches or max_batch_id_now < marker.max_batch_id):
            lost = (f"the database file {self.path} holds {batches_now} batches (highest id "
                    f"{max_batch_id_now}) but {self._recorded(marker)}")
            if not allow_new:
                raise StationError(f"{lost}; {self._what_to_do()}")
            log.warning("%s; continuing with this database as asked (%s)", lost, NEW_DATABASE_FLAG)
            fresh = True
        created = None if fresh or marker is None else marker.created_utc
        if schema is None and marker is not None:
            schema = marker.schema
        self._write_marker(batches_now, max_batch_id_now, schema=schema, created_utc=created)

    # -- internals --------------------------------------------------------------------------------

    def _marker_or_none(self, allow_new: bool) -> Marker | None:
        try:
            return self.read_marker()
        except StationError as exc:
            if not allow_new:
                raise
            log.warning("%s; ignored as asked (%s)", exc, NEW_DATABASE_FLAG)
            return None

    def _recorded(self, marker: Marker) -> str:
        return (f"{self.marker_path.name} recorded {marker.batches} batches (highest id {marker.max_batch_id}) "
                f"on {marker.updated_utc}")

    def _what_to_do(self) -> str:
        return (f"restore the file from a backup or from a rescued copy ({self.path.name}.rescued-*), or start "
                f"with {NEW_DATABASE_FLAG} to begin a new database")

    def _write_marker(self, batches: int, max_batch_id: int, *, schema: str | None,
                      created_utc: str | None) -> None:
        now = _iso(_utc_now())
        data = {"path": str(self.path), "created_utc": created_utc or now, "updated_utc": now,
                "batches": int(batches), "max_batch_id": int(max_batch_id), "schema": schema}
        target = self.marker_path
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(data, f, indent=2)
                f.write("\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _fsync_dir(target.parent)

    def _open_fd(self) -> int | None:
        """A descriptor (of this process) open on the file identified at `opened()`: the cached one
        if fstat still says so, else one found by scanning /proc/self/fd (fstat on each, no open)."""
        identity = self._identity
        if identity is None:
            return None
        with self._lock:
            fd = self._fd
            if fd is not None and _fd_identity(fd) == identity:
                return fd
            self._fd = None
            for fd in _proc_fds():
                if _fd_identity(fd) == identity:
                    self._fd = fd
                    return fd
        return None

    def _open_location(self) -> tuple[bool, str] | None:
        """(unlinked, current name) of the file still open, None if no descriptor is found."""
        fd = self._open_fd()
        if fd is None:
            return None
        try:
            st = os.fstat(fd)
            name = os.readlink(PROC_FD / str(fd))
        except OSError:
            return None
        unlinked = st.st_nlink == 0 or name.endswith(DELETED_SUFFIX)
        return unlinked, name.removesuffix(DELETED_SUFFIX)

    def _wal_fd(self, db_fd: int) -> int | None:
        """The descriptor SQLite holds on the database's -wal (named after the database's real path
        when it was opened), deleted or not."""
        names: set[str] = set()
        for base in {self._real, str(self.path), _fd_name(db_fd) or ""}:
            if base:
                names |= {base + "-wal", base + "-wal" + DELETED_SUFFIX}
        for fd in _proc_fds():
            if fd != db_fd and _fd_name(fd) in names:
                return fd
        return None

    def _copy_consistent(self, fd: int, wal_fd: int | None, copy: Path) -> None:
        """Database then WAL bytes into `copy` and `copy`-wal, retried while the WAL is restarted
        underneath (see the module docstring for why one WAL generation makes a consistent pair)."""
        identity = self._identity
        wal_copy = copy.with_name(copy.name + "-wal")
        for _attempt in range(_COPY_ATTEMPTS):
            before = _pread_all(wal_fd, _WAL_HEADER_BYTES) if wal_fd is not None else b""
            _copy_fd(fd, copy)
            if wal_fd is not None:
                _copy_fd(wal_fd, wal_copy)
            else:
                wal_copy.unlink(missing_ok=True)
            after = _pread_all(wal_fd, _WAL_HEADER_BYTES) if wal_fd is not None else b""
            copied_head = b""
            if wal_fd is not None:
                with open(wal_copy, "rb") as f:
                    copied_head = f.read(_WAL_HEADER_BYTES)
            if _fd_identity(fd) != identity:  # the descriptor was closed (and maybe reused) meanwhile
                raise StationError(f"rescue of {self.path}: the open database was closed during the copy")
            if before == after == copied_head:
                return
        raise StationError(f"rescue of {self.path}: the WAL kept restarting during {_COPY_ATTEMPTS} copies; "
                           f"pause the station's writes and try again")

    def _rescue_target(self) -> Path:
        stamp = _utc_now().strftime("%Y%m%dT%H%M%S")
        base = self.path.with_name(f"{self.path.name}.rescued-{stamp}")
        target, n = base, 1
        while target.exists():
            n += 1
            target = base.with_name(f"{base.name}-{n}")
        return target


def _proc_fds() -> list[int]:
    try:
        names = os.listdir(PROC_FD)
    except OSError:
        return []
    return sorted(int(n) for n in names if n.isdigit())


def _fd_identity(fd: int) -> tuple[int, int] | None:
    try:
        st = os.fstat(fd)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _fd_name(fd: int) -> str | None:
    try:
        return os.readlink(PROC_FD / str(fd))
    except OSError:
        return None


def _pread_all(fd: int, limit: int | None = None) -> bytes:
    out = bytearray()
    while limit is None or len(out) < limit:
        want = _COPY_CHUNK if limit is None else min(_COPY_CHUNK, limit - len(out))
        chunk = os.pread(fd, want, len(out))
        if not chunk:
            break
        out += chunk
    return bytes(out)


def _copy_fd(fd: int, dest: Path) -> None:
    """pread() from a descriptor someone else owns: no seek (SQLite's offsets are untouched) and
    no new descriptor of the file opened or closed (its POSIX locks survive)."""
    with open(dest, "wb") as out:
        offset = 0
        while True:
            chunk = os.pread(fd, _COPY_CHUNK, offset)
            if not chunk:
                break
            out.write(chunk)
            offset += len(chunk)
        out.flush()


def _fsync_dir(directory: Path) -> None:
    try:
        dfd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)

