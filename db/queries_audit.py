"""The audit trail: who did what (REST API actions, the station's own supersessions, limit sets).

Why a module of its own: the writer appends to it inside its own transaction (a superseded verdict
is audited with the record that supersedes it), the web and the daemon append and list; a module
they can all import without pulling in the rest of the read side.
"""

from __future__ import annotations

from collections.abc import Mapping

from sqlalchemy import insert, select
from sqlalchemy.engine import Connection

from contracts.json_safe import plain_json
from db.database import Database
from db.models import AuditRow, utcnow
from db.row_json import JsonAnswer, iso

def audit_append(db: Database, actor: str, action: str, target: str = "", detail: Mapping[str, object] | None = None,
                 station: str | None = None, conn: Connection | None = None) -> int:
    """One audit row (who did what); station defaults to the database's. With `conn` the row goes
    into that connection's transaction (the db writer's: it is stored with what it records, and a
    second transaction would wait on SQLite's write lock the writer holds)."""
    values: dict[str, object] = {"at": utcnow(), "station": (station if station is not None else getattr(db, "station", "")) or "",
              "actor": actor[:128], "action": action[:64], "target": target[:128], "detail": plain_json(detail or {})}
    if conn is not None:
        return int(conn.execute(insert(AuditRow).values(**values)).inserted_primary_key[0])
    with db.session() as s:
        return int(s.execute(insert(AuditRow).values(**values)).inserted_primary_key[0])


def audit_list(db: Database, limit: int = 100, before_id: int | None = None, station: str | None = None) -> list[JsonAnswer]:
    """Audit rows, newest first; page back with before_id = the last id of a page."""
    with db.session() as s:
        q = select(AuditRow).order_by(AuditRow.id.desc()).limit(max(1, min(int(limit), 1000)))
        if before_id is not None:
            q = q.where(AuditRow.id < int(before_id))
        if station:
            q = q.where(AuditRow.station == station)
        return [{"id": a.id, "at": iso(a.at), "station": a.station, "actor": a.actor, "action": a.action,
                 "target": a.target, "detail": a.detail or {}} for a in s.scalars(q)]


__all__ = ["audit_append", "audit_list"]
