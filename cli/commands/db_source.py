"""Which database a command reads, and opening it without ever creating it: a typo in a path must never make an empty database look like a real one.

A command that reads a database (certificate, export, db check|export|prune, replay's source)
opens an existing one only. The URL comes from the command's own option (`--db`, `--url`,
`--source-db`: a SQLite file path or any SQLAlchemy URL), else $STATION_DB_URL, else the
`database_url` of `--config FILE`, else the station default `sqlite:///var/station.db` (relative
to the working directory). A SQLite file that is not there is one line naming where it looked, and
nothing is created on disk (no file, no `var/` folder): `open_existing` checks the file before any
engine exists, and a read opens SQLite with `mode=ro` (db/database.py make_read_only_engine).
Other URLs (PostgreSQL) are servers, not files: they are left to the server to refuse, and a read
runs in read-only transactions.

Only the commands whose job is to create or migrate a database create one: `station db upgrade`,
`serve` and `demo` (they own theirs), and a replay's results database (`replay --db` given beside
`--source-db`, or `var/replay.db` for logs).
"""

from __future__ import annotations

import argparse
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from contracts.types import StationError

DEFAULT_URL = "sqlite:///var/station.db"
ENV = "STATION_DB_URL"
NEVER_CREATED = "a command that reads a database never creates one"
_MEMORY = ("", ":memory:")


@dataclass(frozen=True)
class DbChoice:
    """A database URL and where it came from ("--db x.db", "$STATION_DB_URL", ...)."""

    url: str
    origin: str
    flag: str = "--db"
    default: bool = False  # no option, no environment, no config: the station default
    consulted: tuple[str, ...] = ()  # what was looked at before the default, for the error


def plain_url(url: str) -> str:
    """db.database.plain_url (a URL without its password, for messages), the commands' message
    helper: imported when first called, so that `station --help` does not load SQLAlchemy."""
    from db.database import plain_url as _plain_url

    return _plain_url(url)


def to_url(value: str) -> str:
    """A SQLite file path or a URL -> a URL (a path as given; a relative path stays relative)."""
    if "://" in value:
        return value
    return f"sqlite:///{value}"


def _config_url(path: Path) -> str | None:
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StationError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise StationError(f"{path}: cannot read config ({exc})") from None
    url = data.get("database_url") or (data.get("db") or {}).get("url")
    return str(url) if url else None


def choose(given: str | None, flag: str = "--db", config: str | None = None) -> DbChoice:
    """The database a command was asked for: `given` (its option), else $STATION_DB_URL, else the
    config's database_url, else the station default. Nothing is opened here."""
    if given:
        shown = plain_url(given) if "://" in given else given
        return DbChoice(to_url(given), f"{flag} {shown}", flag)
    if os.environ.get(ENV):
        return DbChoice(to_url(os.environ[ENV]), f"from ${ENV}", flag)
    consulted = [f"no {flag}", f"${ENV} is not set"]
    if config:
        url = _config_url(Path(config))
        if url:
            return DbChoice(to_url(url), f"database_url in {config}", flag)
        consulted.append(f"{config} has no database_url")
    return DbChoice(DEFAULT_URL, "the default", flag, default=True, consulted=tuple(consulted))


def sqlite_file(url: str) -> Path | None:
    """The file of a SQLite URL (None for a server URL such as PostgreSQL). An in-memory SQLite
    database has nothing to read: StationError."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    if url.startswith("memory://"):
        raise StationError(f"{url} is an empty in-memory database: nothing to read; {NEVER_CREATED}")
    try:
        u = make_url(url)
    except ArgumentError:
        raise StationError(f"{url!r} is neither a database URL nor a SQLite file path") from None
    if u.get_backend_name() != "sqlite":
        return None
    database = u.database or ""
    if database in _MEMORY:
        raise StationError(f"{url} is an empty in-memory database: nothing to read; {NEVER_CREATED}")
    if database.startswith("file:"):  # sqlite:///file:PATH?uri=true
        database = database[len("file:"):]
    return Path(database).expanduser()


def require_existing(choice: DbChoice) -> None:
    """One line (StationError) when the chosen SQLite file is not there; nothing is touched."""
    path = sqlite_file(choice.url)
    if path is None or path.is_file():
        return
    where = path.resolve()
    if choice.default:
        raise StationError(f"no database given ({', '.join(choice.consulted)}) and none at the default "
                           f"{path} ({where}): give {choice.flag} PATH|URL; {NEVER_CREATED}")
    if path.is_dir():
        raise StationError(f"{where} ({choice.origin}) is a directory, not a database file")
    raise StationError(f"database {where} ({choice.origin}): no such file; {NEVER_CREATED}")


def open_existing(choice: DbChoice, write: bool = False) -> Any:
    """The chosen database, which must exist, at this software's schema (Database.check):
    read-only unless `write` (db prune); never created, never migrated."""
    from db.database import Database

    require_existing(choice)
    try:
        db = Database(choice.url, read_only=not write)
    except StationError:
        raise
    except Exception as exc:  # noqa: BLE001 - a bad URL or a missing driver: one line
        raise StationError(f"database {plain_url(choice.url)}: {type(exc).__name__}: {exc}") from None
    from sqlalchemy.exc import DatabaseError

    try:
        if db.current_revision() is None:  # an empty file (or schema): nothing to read, nothing migrated
            raise StationError(f"database {plain_url(choice.url)} ({choice.origin}) holds no station data "
                               "(no schema; `station db upgrade` gives it an empty one)")
        db.check()
    except DatabaseError as exc:  # "file is not a database": a file that is not SQLite's
        db.dispose()
        raise StationError(f"cannot read database {plain_url(choice.url)} ({choice.origin}): "
                           f"{getattr(exc, 'orig', None) or exc}") from None
    except StationError as exc:  # an outdated schema, a server that refuses: the URL without its password
        db.dispose()
        raise StationError(str(exc).replace(choice.url, plain_url(choice.url))) from None
    except BaseException:
        db.dispose()
        raise
    return db


def choose_from_args(args: argparse.Namespace, attr: str = "db", flag: str = "--db") -> DbChoice:
    return choose(getattr(args, attr, None), flag, getattr(args, "config", None))
