"""One station owns its database, its ports and its relay.

Why: nothing stopped a second process from using the hardware of a running station. A
`station serve --check` on the config of a running daemon marked its batch interrupted (error
records to the MES), switched the lamp relay off under it and opened its serial ports (pyserial
opens are not exclusive), so every slot of the running batch faulted. Now a station first claims
every resource its config names, before anything touches the database or the hardware, and holds
the claim for the life of the process; a second claimant is refused in one line that names the
owner (its PID, host and since when), and touches nothing.

How, per resource:
- local resources (the SQLite file, serial ports, CAN channels, Modbus endpoints, the config file):
  `fcntl.flock(LOCK_EX | LOCK_NB)` on a lock file. The kernel drops the lock when the process dies
  (SIGKILL, OOM, power loss of the PC), so a dead owner never leaves a stale lock behind; the file
  itself stays and only says who held it last (JSON: pid, host, command, station, resource, since),
  rewritten by each new owner. Lock files of ports and endpoints live in one directory
  (`lock_dir` in the config, default per user); the SQLite lock file sits next to the database
  (`station.db.owner`), so two processes with different lock directories still collide on it.
- PostgreSQL (a line of stations shares one database, each station by its `name`): a session-level
  `pg_try_advisory_lock` keyed on the station name, on a dedicated connection kept open; its
  `application_name` carries the owner's PID and host, so a refusal can name the holder from
  `pg_stat_activity`. PostgreSQL drops the lock when that connection ends (process death).

The core (which resources a config names, lock file names, the refusal's words) is pure; only
`StationClaim.take` does I/O.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import errno
import fcntl
import hashlib
import json
import os
import re
import socket
import sys
import time
from pathlib import Path
from typing import Protocol

from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError

from contracts.filenames import safe_name
from contracts.types import StationError
from db.database import plain_url
from station.config import ModbusDevice, StationConfig

__all__ = ["ClaimRefused", "Owner", "Resource", "StationClaim", "command_label", "database_url_of",
           "default_lock_dir", "refusal_text", "station_resources"]

# How many held resources a refusal names before "and N more": the line stays readable.
MAX_NAMED = 3
# A claimant that finds a lock file empty waits this long for its new owner to write it (wall s).
OWNER_READ_WAIT_S = 0.3
# PostgreSQL: how long the claim waits for the server (wall s); application_name is 63 bytes at most.
PG_CONNECT_TIMEOUT_S = 5
PG_APP_NAME_MAX = 63
_PG_KEY_PREFIX = b"accel-station name\0"


# ----------------------------------------------------------------------------------- data
@dataclasses.dataclass(frozen=True)
class Resource:
    """One thing only one station may use. `key` is its identity (a resolved path, `tcp host:port`,
    a station name on a database); `label` is how a refusal names it. `lock_path` is the lock file
    of a local resource; None for the station name on PostgreSQL (`pg_url` set instead)."""

    kind: str
    key: str
    label: str
    lock_path: Path | None = None
    pg_url: str | None = None


@dataclasses.dataclass(frozen=True)
class Owner:
    """Who holds (or last held) a resource: what its lock file says, or what PostgreSQL reports."""

    pid: int | None
    host: str
    command: str = ""
    station: str = ""
    resource: str = ""
    started_at: str = ""  # RFC 3339 UTC, e.g. 2026-11-27T10:01:02Z
    argv: tuple[str, ...] = ()

    def describe(self) -> str:
        """'station serve (PID 4242 on host line3-pc, since 2026-11-27 10:01:02 UTC)'."""
        who = self.command or "another process"
        facts = [f"PID {self.pid}" if self.pid is not None else "PID unknown"]
        facts[0] += f" on host {self.host}" if self.host else ""
        if self.started_at:
            facts.append("since " + self.started_at.replace("T", " ").replace("Z", " UTC"))
        return f"{who} ({', '.join(facts)})"

    def to_json(self) -> str:
        return json.dumps({"pid": self.pid, "host": self.host, "command": self.command, "argv": list(self.argv),
                           "station": self.station, "resource": self.resource, "started_at": self.started_at})

    @classmethod
    def from_json(cls, text: str) -> "Owner | None":
        try:
            data = json.loads(text)
            pid = data.get("pid")
            return cls(pid=int(pid) if pid is not None else None, host=str(data.get("host", "")),
                       command=str(data.get("command", "")), station=str(data.get("station", "")),
                       resource=str(data.get("resource", "")), started_at=str(data.get("started_at", "")),
                       argv=tuple(str(a) for a in data.get("argv", [])))
        except (ValueError, TypeError, AttributeError):
            return None


class ClaimRefused(StationError):
    """Another process holds some of this station's resources (one line, exit non-zero)."""

    def __init__(self, held: list[tuple[Resource, Owner | None]]) -> None:
        super().__init__(refusal_text(held))
        self.held = held


# ----------------------------------------------------------------------------------- pure core
def rfc3339_utc(epoch_s: float) -> str:
    return dt.datetime.fromtimestamp(epoch_s, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def command_label(argv: list[str] | None = None) -> str:
    """What a refusal calls the owner: `station serve`, `station demo`, or the program's name."""
    argv = list(sys.argv if argv is None else argv)
    if not argv:
        return "python"
    prog = os.path.basename(argv[0])
    if prog == "__main__.py":  # python -m PACKAGE
        prog = os.path.basename(os.path.dirname(argv[0]))
    if prog.startswith("-"):  # python -c
        return "python"
    if prog in ("station", "cli.py") and len(argv) > 1 and not argv[1].startswith("-"):
        return f"station {argv[1]}"
    return prog or "python"


def default_lock_dir() -> Path:
    """Per user: $XDG_RUNTIME_DIR/accel-station (cleared at logout/boot, like the locks), else
    /tmp/accel-station-locks-<uid>."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isdir(runtime):
        return Path(runtime) / "accel-station"
    return Path(f"/tmp/accel-station-locks-{os.getuid()}")


def lock_file_name(kind: str, key: str) -> str:
    """A safe file name of one resource (contracts/filenames.py: a value that is not a clean name
    carries its hash, so two resources never share a lock file)."""
    return safe_name(f"{kind}-{key}") + ".lock"


def _parsed(url: str) -> URL | None:
    try:
        return make_url(url)
    except ArgumentError:
        return None


def sqlite_path(url: str) -> Path | None:
    """The file of a SQLite URL (absolute, `~` expanded as the engine does, symlinks resolved);
    None for an in-memory or temporary database and for anything else."""
    u = _parsed(url)
    if u is None or u.get_backend_name() != "sqlite":
        return None
    database = u.database or ""
    if database in ("", ":memory:") or database.startswith("file:"):
        return None
    return Path(os.path.realpath(Path(database).expanduser()))


def is_postgres(url: str) -> bool:
    u = _parsed(url)
    return u is not None and u.get_backend_name() == "postgresql"


def _port_key(port: str) -> str | None:
    """A serial port's identity: its resolved path (two symlinks to one tty collide); a pyserial
    URL as written; None for `loop://` (private to its process: nothing to share)."""
    if "://" in port:
        return None if port.startswith("loop://") else port
    return os.path.realpath(port)


def _modbus_key(dev: ModbusDevice) -> str:
    if dev.tcp is not None:
        host = dev.tcp.host.strip().lower()
        return f"tcp {'127.0.0.1' if host == 'localhost' else host}:{dev.tcp.port}"
    assert dev.rtu is not None
    return f"rtu {_port_key(dev.rtu.port) or dev.rtu.port}"


def station_resources(cfg: StationConfig, *, database_url: str | None, config_path: str | Path | None = None,
                      lock_dir: Path | None = None) -> list[Resource]:
    """Every resource the config names, each once (devices on one Modbus endpoint, CAN slots on one
    adapter share one), in the order a refusal names them: database first.

    A replay's station (`replay_of` set, station/replay) claims its simulated links only, not the
    database: it stores replays beside the live station's batches (and under its name) while that
    station runs, marks nothing interrupted and never touches the line's hardware."""
    locks = lock_dir or (Path(cfg.lock_dir).expanduser() if cfg.lock_dir else default_lock_dir())
    out: list[Resource] = []
    url = "" if cfg.replay_of else (database_url or "")
    db_file = sqlite_path(url)
    if db_file is not None:
        out.append(Resource("database", str(db_file), f"the database {db_file}",
                            db_file.with_name(db_file.name + ".owner")))
    elif is_postgres(url):
        out.append(Resource("station name", f"{cfg.name}@{plain_url(url)}",
                            f"the station name {cfg.name!r} on the database {plain_url(url)}", pg_url=url))
    named: dict[tuple[str, str], list[str]] = {}
    for s in cfg.slots:
        if s.serial is not None:
            key = _port_key(s.serial)
            if key is not None:
                named.setdefault(("serial port", key), []).append(f"slot {s.name}")
        elif s.can is not None and s.can.interface != "virtual":  # python-can's virtual bus is in-process
            chan = s.can.channel
            path, sep, baud = chan.partition("@")
            ident = (os.path.realpath(path) + sep + baud) if path.startswith("/") else chan
            named.setdefault(("CAN channel", f"{s.can.interface}:{ident}"), []).append(f"slot {s.name}")
    for role, dev in (("lamp relay", cfg.lamp), ("fixture", cfg.fixture), ("thermometer", cfg.thermometer),
                      ("chamber", cfg.chamber)):
        if dev is not None:
            named.setdefault(("Modbus endpoint", _modbus_key(dev)), []).append(role)
    for (kind, key), users in named.items():
        if kind == "serial port":
            label = f"the serial port {key} ({', '.join(users)})"
        elif kind == "CAN channel":
            label = f"the CAN channel {key} ({len(users)} slot{'s' if len(users) > 1 else ''})"
        else:
            label = f"the {' and '.join(users)} at modbus {key}"
        out.append(Resource(kind, key, label, locks / lock_file_name(kind, key)))
    if config_path is not None:
        key = os.path.realpath(config_path)
        out.append(Resource("config file", key, f"the config {key}", locks / lock_file_name("config file", key)))
    return out


def refusal_text(held: list[tuple[Resource, Owner | None]]) -> str:
    """'the database /x/station.db is held by station serve (PID 4242 on host line3-pc, since ...):
    one station owns its boards, relay and database; stop it first'. Resources of one holder are
    named together, at most MAX_NAMED, then 'and N more'."""
    groups: dict[str, list[str]] = {}
    for res, owner in held:
        who = owner.describe() if owner is not None else "another process (owner not known yet)"
        groups.setdefault(who, []).append(res.label)
    parts = []
    for who, labels in groups.items():
        names = labels[:MAX_NAMED]
        more = len(labels) - len(names)
        if more:
            listed = ", ".join(names) + f" and {more} more"
        else:
            listed = " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)
        verb = "is" if len(labels) == 1 else "are"
        parts.append(f"{listed} {verb} held by {who}")
    return "; ".join(parts) + ": one station owns its boards, relay and database; stop it first"


# ----------------------------------------------------------------------------------- PostgreSQL
def pg_lock_key(station_name: str) -> int:
    """The advisory lock key of a station name: 64 bits of its hash, signed (bigint)."""
    return int.from_bytes(hashlib.sha256(_PG_KEY_PREFIX + station_name.encode()).digest()[:8], "big", signed=True)


def _pg_app_name(owner: Owner) -> str:
    return f"accel-station pid={owner.pid} host={owner.host} {owner.command}"[:PG_APP_NAME_MAX]


class _Cursor(Protocol):
    def fetchone(self) -> tuple[object, ...] | None: ...


class _PgConnection(Protocol):
    def execute(self, query: str, params: tuple[object, ...] = ...) -> _Cursor: ...

    def close(self) -> None: ...


def _pg_connect(url: str, app_name: str) -> _PgConnection:
    import psycopg

    conninfo = make_url(url).set(drivername="postgresql").render_as_string(hide_password=False)
    try:
        conn: _PgConnection = psycopg.connect(conninfo, autocommit=True, application_name=app_name,
                                              connect_timeout=PG_CONNECT_TIMEOUT_S)
    except psycopg.Error as exc:
        raise StationError(f"database {plain_url(url)}: {type(exc).__name__}: {str(exc).strip()}") from None
    return conn


def _pg_holder(conn: _PgConnection, key: int) -> Owner | None:
    """Who holds the advisory lock `key` in this database (pg_locks + pg_stat_activity)."""
    unsigned = key & 0xFFFF_FFFF_FFFF_FFFF
    row = conn.execute(
        "SELECT a.pid, a.application_name, host(a.client_addr), a.backend_start "
        "FROM pg_locks l JOIN pg_stat_activity a ON a.pid = l.pid "
        "WHERE l.locktype = 'advisory' AND l.granted AND l.objsubid = 1 "
        "AND l.database = (SELECT oid FROM pg_database WHERE datname = current_database()) "
        "AND l.classid::bigint = %s AND l.objid::bigint = %s",
        (unsigned >> 32, unsigned & 0xFFFF_FFFF)).fetchone()
    if row is None:
        return None
    backend_pid, app, client, since = row
    m = re.match(r"accel-station pid=(\d+) host=(\S+) ?(.*)$", str(app or ""))
    started = rfc3339_utc(since.timestamp()) if isinstance(since, dt.datetime) else ""
    if m:
        return Owner(pid=int(m.group(1)), host=m.group(2), command=m.group(3), started_at=started)
    return Owner(pid=None, host=str(client or ""), command=f"PostgreSQL session {backend_pid} ({app or 'no name'})",
                 started_at=started)


# ----------------------------------------------------------------------------------- the claim
def database_url_of(db: object) -> str | None:
    """The URL of the database a Station really uses; None for a temporary one (nothing to share)."""
    if getattr(db, "temporary_dir", None) is not None:
        return None
    url = getattr(db, "url", None)
    return url if isinstance(url, str) else None


def _prepare_lock_dir(path: Path, configured: bool) -> None:
    """Create the lock directory; the default one (in /tmp) must be a real directory of ours, or
    another user could hand us their lock files."""
    try:
        path.mkdir(mode=0o700, parents=configured, exist_ok=True)
    except OSError as exc:
        raise StationError(f"lock directory {path}: {exc.strerror}") from None
    if not configured:
        st = os.lstat(path)
        if not os.path.isdir(path) or os.path.islink(path) or st.st_uid != os.getuid():
            raise StationError(f"lock directory {path} is not a directory of this user; set lock_dir in the config")


def _read_owner(fd: int) -> Owner | None:
    """The owner a held lock file names; a new owner may be between its lock and its write."""
    end = time.monotonic() + OWNER_READ_WAIT_S
    while True:
        try:
            text = os.pread(fd, 65536, 0).decode("utf-8", "replace")
        except OSError:
            text = ""
        owner = Owner.from_json(text) if text.strip() else None
        if owner is not None or time.monotonic() >= end:
            return owner
        time.sleep(0.02)


class StationClaim:
    """The resources one station holds, exclusively, until `release()` or the process ends.

    `StationClaim.take(cfg, database_url=..., config_path=...)` claims them all or none: when any
    is held elsewhere it releases what it got, writes nothing, and raises ClaimRefused naming every
    held resource and its owner."""

    def __init__(self, resources: list[Resource], owner: Owner) -> None:
        self.resources = resources
        self.owner = owner
        self._fds: list[int] = []
        self._pg: list[_PgConnection] = []

    @classmethod
    def take(cls, cfg: StationConfig, *, database_url: str | None, config_path: str | Path | None = None,
             command: str | None = None, lock_dir: Path | None = None) -> "StationClaim":
        resources = station_resources(cfg, database_url=database_url, config_path=config_path, lock_dir=lock_dir)
        owner = Owner(pid=os.getpid(), host=socket.gethostname(), command=command or command_label(),
                      station=cfg.name, started_at=rfc3339_utc(time.time()), argv=tuple(sys.argv))
        claim = cls(resources, owner)
        configured = lock_dir is not None or bool(cfg.lock_dir)
        claim._acquire(configured)
        return claim

    def _acquire(self, lock_dir_configured: bool) -> None:
        held: list[tuple[Resource, Owner | None]] = []
        got: list[tuple[Resource, int]] = []
        prepared: set[Path] = set()
        try:
            for res in self.resources:
                if res.lock_path is not None:
                    folder = res.lock_path.parent
                    if res.kind != "database" and folder not in prepared:
                        _prepare_lock_dir(folder, lock_dir_configured)
                        prepared.add(folder)
                    fd, holder = self._lock_file(res.lock_path)
                    if fd is None:
                        held.append((res, holder))
                    else:
                        got.append((res, fd))
                elif res.pg_url is not None:
                    conn, holder = self._lock_pg(res.pg_url)
                    if conn is None:
                        held.append((res, holder))
                    else:
                        self._pg.append(conn)
        except BaseException:
            for _, fd in got:
                os.close(fd)
            self._close_pg()
            raise
        if held:  # all or nothing, and nothing written: the files keep naming their owners
            for _, fd in got:
                os.close(fd)
            self._close_pg()
            raise ClaimRefused(held)
        for res, fd in got:
            text = dataclasses.replace(self.owner, resource=res.label).to_json() + "\n"
            os.ftruncate(fd, 0)
            os.pwrite(fd, text.encode(), 0)
            self._fds.append(fd)

    @staticmethod
    def _lock_file(path: Path) -> tuple[int | None, Owner | None]:
        """(fd, None) when locked here; (None, owner) when another open file holds it."""
        if path.parent.name and not path.parent.exists():
            path.parent.mkdir(parents=True, exist_ok=True)  # a database folder not created yet
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise StationError(f"cannot open lock file {path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                os.close(fd)
                raise StationError(f"cannot lock {path}: {exc.strerror}") from None
            owner = _read_owner(fd)
            os.close(fd)
            return None, owner
        return fd, None

    def _lock_pg(self, url: str) -> tuple[_PgConnection | None, Owner | None]:
        conn = _pg_connect(url, _pg_app_name(self.owner))
        try:
            key = pg_lock_key(self.owner.station)
            row = conn.execute("SELECT pg_try_advisory_lock(%s)", (key,)).fetchone()
            if row is not None and row[0] is True:
                return conn, None
            holder = _pg_holder(conn, key)
        except BaseException:
            conn.close()
            raise
        conn.close()
        return None, holder

    def _close_pg(self) -> None:
        for conn in self._pg:
            try:
                conn.close()  # the session ends: PostgreSQL drops its advisory lock
            except Exception:  # noqa: BLE001 - a connection already gone holds no lock either
                pass
        self._pg = []

    @property
    def held(self) -> bool:
        return bool(self._fds or self._pg)

    def release(self) -> None:
        """Give everything back (idempotent). The lock files stay: deleting one another process
        has just opened would let two owners lock two different files of one name."""
        fds, self._fds = self._fds, []
        for fd in fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._close_pg()

    def __del__(self) -> None:  # a Station dropped without close() (a failed start) lets go too
        try:
            self.release()
        except Exception:  # noqa: BLE001 - interpreter shutdown: the kernel lets go anyway
            pass
