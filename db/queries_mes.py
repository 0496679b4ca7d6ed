"""The MES side: the results feed (results_since) and the outbox the webhook delivers from.

Why a module of its own: these are the station's promises to the MES (docs/records.md): every
verdict record reaches it once, in commit order, under one idempotency key (db/mes_record.py
mes_key), and a message queued twice (two stations' workers) is one outbox row.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime

from sqlalchemy import select, update

from contracts.types import NotFound
from contracts.json_safe import plain_json

from db.database import Database
from db.engine import insert_ignore
from db.mes_record import mes_key, revision_of
from db.models import Batch, Dut, DutRun, Outbox, VerdictHistoryRow, utcnow
from db.row_json import JsonAnswer, iso, outbox_json, record_verdict_json, run_results, trace_json

def results_since(db: Database, since: int = 0, limit: int = 100, since_time: datetime | None = None,
                  station: str | None = None) -> list[JsonAnswer]:
    """The MES feed: verdict records (a run's final verdict, and each later one that supersedes it)
    stored after cursor `since`, in increasing `id` (= the record's result_seq). Page on with
    since = the last id. Safe with many stations writing: result_seq is taken in commit order
    (db/mes_record.py take_result_seq), so a record committed after this read gets a number above every
    one returned here. Each record carries `revision` (1, 2, ... per run) and `supersedes` (the
    idempotency key of the record it replaces, or None): a client keeps the latest revision per
    run_id. since_time (optional) also requires the record to be judged at/after that time."""
    H = VerdictHistoryRow
    limit = max(1, min(int(limit), 1000))
    with db.session() as s:
        q = (
            select(H, revision_of(H.run_id, H.result_seq), DutRun, Dut.serial, Batch)
            .join(DutRun, DutRun.id == H.run_id)
            .join(Dut, Dut.id == DutRun.dut_id)
            .join(Batch, Batch.id == DutRun.batch_id)
            .where(H.result_seq > int(since))
            .order_by(H.result_seq)
            .limit(limit)
        )
        if station:
            q = q.where(DutRun.station == station)
        if since_time is not None:
            q = q.where(H.judged_at >= since_time)
        out = []
        for h, rev, r, serial, b in s.execute(q).all():
            item = {
                "id": h.result_seq,
                "idempotency_key": mes_key(r.id, h.result_seq),
                "revision": int(rev),
                "supersedes_seq": h.supersedes_seq,
                "supersedes": None if h.supersedes_seq is None else mes_key(r.id, h.supersedes_seq),
                "created_at": iso(h.judged_at),
                "run_id": r.id,
                "batch_id": r.batch_id,
                "station": r.station,
                "slot": r.slot,
                "serial": serial,
                "sensor": (r.identity or {}).get("sensor"),
                "profile": b.profile,
                "operator": b.operator,
                "state": r.state,
                "ended_at": iso(r.ended_at),
                **trace_json(b, with_labels=False),
                "label_serial": r.label_serial,
                # tested without the MES's yes ('unanswered', policy proceed_and_flag) is the MES's to know
                "route_check": r.route_check,
                "route_reason": r.route_reason or "",
                **record_verdict_json(h, r.attempt),
            }
            item.update(run_results(s, r.id))
            out.append(item)
        return out


def outbox_enqueue(db: Database, idempotency_key: str, payload: Mapping[str, object], topic: str = "result") -> int:
    """Queue a message; enqueueing the same key again returns the existing message's id. Insert-or-get
    by the database itself (ON CONFLICT DO NOTHING): two stations' MES workers may enqueue the same
    record at the same moment."""
    return outbox_enqueue_new(db, idempotency_key, payload, topic)[0]


def outbox_enqueue_new(db: Database, idempotency_key: str, payload: Mapping[str, object], topic: str = "result") -> tuple[int, bool]:
    """(message id, True when this call queued it; False when the key was queued already)."""
    now = utcnow()
    with db.session() as s:
        res = s.execute(insert_ignore(s, Outbox, ["idempotency_key"]).values(
            idempotency_key=idempotency_key, topic=topic, payload=plain_json(payload), attempts=0,
            next_attempt_at=now, last_error="", created_at=now,
        ))
        added = bool(res.rowcount)
        oid = s.scalar(select(Outbox.id).where(Outbox.idempotency_key == idempotency_key))
        return int(oid), added


def outbox_pending(db: Database, limit: int = 50, now: datetime | None = None, topic: str = "result") -> list[JsonAnswer]:
    """Undelivered messages of `topic` due now (next_attempt_at <= now), oldest first. The webhook's
    topic is "result"; the CFX worker's messages (topic "cfx", db/queries_cfx.py) share the table and
    are never the webhook's to send."""
    now = now or utcnow()
    with db.session() as s:
        rows = s.scalars(
            select(Outbox)
            .where(Outbox.delivered_at.is_(None), Outbox.next_attempt_at <= now, Outbox.topic == topic)
            .order_by(Outbox.next_attempt_at, Outbox.id)
            .limit(max(1, limit))
        ).all()
        return [outbox_json(o) for o in rows]


def outbox_mark_delivered(db: Database, outbox_id: int) -> None:
    with db.session() as s:
        res = s.execute(
            update(Outbox).where(Outbox.id == outbox_id)
            .values(delivered_at=utcnow(), attempts=Outbox.attempts + 1, last_error="")
        )
        if res.rowcount == 0:
            raise NotFound(f"no outbox message {outbox_id}")


def outbox_mark_failed(db: Database, outbox_id: int, error: str, next_attempt_at: datetime) -> None:
    """One failed delivery: count it, keep the error, retry at next_attempt_at (caller's backoff)."""
    with db.session() as s:
        res = s.execute(
            update(Outbox).where(Outbox.id == outbox_id)
            .values(attempts=Outbox.attempts + 1, last_error=str(error)[:2000], next_attempt_at=next_attempt_at)
        )
        if res.rowcount == 0:
            raise NotFound(f"no outbox message {outbox_id}")


__all__ = ["results_since", "outbox_enqueue", "outbox_enqueue_new", "outbox_pending", "outbox_mark_delivered",
           "outbox_mark_failed"]
