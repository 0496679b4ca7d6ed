"""The database's schema revision: migrate, check, refuse a newer or corrupted database.

Why a module of its own: the schema is owned by the Alembic revisions in db/migrations/versions/,
and what the station does about it at start (upgrade, or only check, refuse what it does not know,
refuse a corrupted file in one line) is one concern, separate from the rows the daemon writes.
`Schema` is a base class of db.database.Database, so `db.upgrade()`, `db.check()` and the rest
keep their names.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import text
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import DatabaseError, OperationalError

from contracts.types import StationError

if TYPE_CHECKING:  # alembic is imported when a schema call needs it, not with the package
    from alembic.config import Config

log = logging.getLogger("db.database")  # the database's own log, as before the split

DB_DIR = Path(__file__).resolve().parent
ALEMBIC_INI = DB_DIR / "alembic.ini"
MIGRATIONS_DIR = DB_DIR / "migrations"


class Schema:
    """Schema revision and integrity of the database behind `engine` (mixed into Database)."""

    url: str
    read_only: bool
    engine: Engine

    @property
    def is_sqlite(self) -> bool:
        return self.engine.dialect.name == "sqlite"

    def _alembic_config(self, connection: Connection | None = None) -> Config:
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

    def sqlite_integrity_check(self) -> str:
        """`PRAGMA integrity_check` ('ok' when sound); 'n/a' on other databases."""
        if not self.is_sqlite:
            return "n/a"
        with self.engine.connect() as conn:
            return str(conn.exec_driver_sql("PRAGMA integrity_check").scalar())


__all__ = ["Schema", "ALEMBIC_INI", "MIGRATIONS_DIR"]
