"""How the station connects to a database backend: engines, URLs, and the two dialect helpers.

Why a module of its own: everything here depends on the backend (SQLite or PostgreSQL), nothing on
the schema or the station's records. db/database.py (the Database class) and the writer build on it.

SQLite durability: journal_mode=WAL with synchronous=FULL. WAL alone already survives a killed
process (a commit is in the WAL file before COMMIT returns); FULL adds an fsync of the WAL on every
commit, so an acknowledged commit also survives a power cut or kernel panic, which a factory station
must expect. The cost is one fsync per writer transaction, and the writer batches ~0.2 s of events
per transaction, so it is a handful of fsyncs per second.

PostgreSQL: nothing the station asks may wait for ever: a hung call would stop the station with it. A server that is down is met
in connect_timeout; a statement or a lock that takes too long is ended by the server; a
connection whose peer vanished (a network cut, a host that died) is found by TCP keepalives and
tcp_user_timeout. A server that is alive but stopped (SIGSTOP, a hung host) answers none of these:
the station's DbProbe (station/daemon/storage.py) says so, the routes fail fast, and the writer's
watchdog journals what waits behind a hung commit.

Concurrent stations on one database: `insert_ignore` lets the database decide who inserts a shared
row (insert-or-get), `retry_collisions` retries a transaction that lost a race the database settles.
"""

from __future__ import annotations

import logging
import random
import sqlite3
import time
from pathlib import Path
from typing import Any, Callable, TypeVar

from sqlalchemy import create_engine, event
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.engine import Connection, Engine, make_url
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session
from sqlalchemy.sql.dml import Insert

from contracts.types import StationError
from db.models import Base

log = logging.getLogger(__name__)

T = TypeVar("T")

SQLITE_SYNCHRONOUS = "FULL"
PG_POOL_TIMEOUT_S = 5.0
PG_CONNECT_ARGS: dict[str, int | str] = {
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


def _sqlite_on_connect(dbapi_conn: sqlite3.Connection, _record: object) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute(f"PRAGMA synchronous={SQLITE_SYNCHRONOUS}")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def _sqlite_read_only_on_connect(dbapi_conn: sqlite3.Connection, _record: object) -> None:
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


def insert_ignore(bind: Session | Connection, model: type[Base], conflict_columns: list[str]) -> Insert:
    """INSERT ... ON CONFLICT (conflict_columns) DO NOTHING for the bind's dialect (SQLite and
    PostgreSQL): the database decides who inserts the row; the loser's insert does nothing and
    waits for the winner's commit on PostgreSQL, so the row can be read right after."""
    name = bind.get_bind().dialect.name if isinstance(bind, Session) else bind.dialect.name
    if name == "postgresql":
        return pg_insert(model).on_conflict_do_nothing(index_elements=conflict_columns)
    if name == "sqlite":
        return sqlite_insert(model).on_conflict_do_nothing(index_elements=conflict_columns)
    raise StationError(f"insert-or-get is not implemented for {name} databases (SQLite, PostgreSQL)")


def _retryable(exc: Exception) -> bool:
    if isinstance(exc, IntegrityError):
        return "unique" in str(exc.orig).lower() or "duplicate" in str(exc.orig).lower()
    if isinstance(exc, OperationalError):
        return getattr(exc.orig, "sqlstate", None) in RETRY_PGCODES or getattr(exc.orig, "pgcode", None) in RETRY_PGCODES
    return False


def retry_collisions(fn: Callable[[], T], what: str, attempts: int = COLLISION_RETRIES,
                     on_retry: Callable[[], None] | None = None) -> T:
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


__all__ = ["SQLITE_SYNCHRONOUS", "PG_CONNECT_ARGS", "PG_POOL_TIMEOUT_S", "plain_url", "make_engine",
           "make_read_only_engine", "insert_ignore", "retry_collisions"]
