"""The identity of one MES record: its cursor (result_seq), its idempotency key, its revision.

Why one module: the MES deduplicates on the idempotency key, so every path that names a record
(the writer's outbox row and audit entry, the results feed, the webhook, a superseding record's
`supersedes`) must build the key the same way, or one record reaches the MES twice under two keys.
`mes_key` is that one place. The record is a run's final verdict (design 8, docs/verdicts.md); a
later verdict of the same run is a new record with a new result_seq (so a new key) and revision N+1.
"""

from __future__ import annotations

from sqlalchemy import SQLColumnExpression, func, insert, select, update
from sqlalchemy.engine import Connection
from sqlalchemy.orm import aliased
from sqlalchemy.sql.selectable import ScalarSelect

from db.models import DutRun, ResultCounter, VerdictHistoryRow


def mes_key(run_id: int, result_seq: int) -> str:
    """THE idempotency key of one verdict record (results feed, webhook, outbox and audit alike):
    `result:<run_id>:<result_seq>`."""
    return f"result:{run_id}:{result_seq}"


def take_result_seq(conn: Connection) -> int:
    """The next MES cursor value, from the one-row counter (db.models.ResultCounter). The UPDATE
    holds the row lock until this transaction commits, so two writers (two stations on one
    PostgreSQL) take numbers in commit order: `results since N` cannot see N+2 before N+1 exists.
    On SQLite the UPDATE takes the database write lock, which gives the same. Call it late in the
    transaction: the lock is held from here to the commit."""
    value = conn.execute(
        update(ResultCounter).where(ResultCounter.id == 1).values(value=ResultCounter.value + 1)
        .returning(ResultCounter.value)
    ).scalar()
    if value is None:  # the row is made by migration 0005; a hand-made schema may lack it
        start = int(conn.execute(select(func.coalesce(func.max(DutRun.result_seq), 0))).scalar_one()) + 1
        conn.execute(insert(ResultCounter).values(id=1, value=start))
        value = start
    return int(value)


def revision_of(run_id: int | SQLColumnExpression[int],
                result_seq: int | SQLColumnExpression[int | None]) -> ScalarSelect[int]:
    """The revision of verdict record (run_id, result_seq) as a scalar subquery: how many records
    the MES has for that run up to and including it (1 = the first final verdict). Columns or
    plain values: the feed asks it per row, the writer for the record it just stored."""
    earlier = aliased(VerdictHistoryRow)
    return (select(func.count(earlier.id)).where(earlier.run_id == run_id, earlier.result_seq.is_not(None),
                                                 earlier.result_seq <= result_seq).scalar_subquery())


__all__ = ["mes_key", "take_result_seq", "revision_of"]
