"""The IPC-CFX side (docs/cfx.md): what a CFX message is made of, read from the stored records, and
the station's CFX messages in the shared `outbox` table (topic "cfx").

Why a module of its own: CFX messages are built only from what the station stored and decided (a
batch row, its runs, a verdict record), never from a live event that may still change, and they
share the MES webhook's durable outbox under their own topic with a per-station key prefix, so the
webhook (db/queries_mes.py outbox_pending, topic "result") never sends them and the CFX worker sends
only its own station's, in id order (the order they were queued in).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime

from sqlalchemy import func, select

from db.database import Database
from db.models import Batch, Dut, DutRun, Outbox, SegmentRow

CFX_TOPIC = "cfx"


@dataclass(frozen=True)
class RunFacts:
    """One run of a batch as a CFX message needs it (a unit at a position)."""

    run_id: int
    slot: str
    serial: str
    state: str
    verdict: str | None
    route_check: str | None
    result_seq: int | None
    started_at: datetime | None
    ended_at: datetime | None


@dataclass(frozen=True)
class BatchFacts:
    """One stored batch as a CFX message needs it. slots: the config's slot names in order (a slot's
    1-based index there is the unit's CFX position number); thermometer: the reference thermometer's
    link when the batch's config had one, with its calibration in the config's words."""

    batch_id: int
    station: str
    profile: str
    operator: str
    state: str
    reason: str
    created_at: datetime
    ended_at: datetime | None
    work_order: str
    lot: str
    slots: tuple[str, ...]
    thermometer: str | None
    thermometer_calibration: str
    runs: tuple[RunFacts, ...] = field(default=())


@dataclass(frozen=True)
class TempStats:
    """The DUT temperatures of a run's stored segments (the test's thermal condition), C."""

    n: int
    mean_c: float
    median_c: float
    min_c: float
    max_c: float


def _link(dev: object) -> str | None:
    """A Modbus device of a config snapshot in words (None: none configured)."""
    if not isinstance(dev, dict):
        return None
    unit = dev.get("unit")
    tcp, rtu = dev.get("tcp"), dev.get("rtu")
    if isinstance(tcp, dict):
        return f"modbus tcp {tcp.get('host')}:{tcp.get('port', 502)} unit {unit}"
    if isinstance(rtu, dict):
        return f"modbus rtu {rtu.get('port')} unit {unit}"
    return f"modbus unit {unit}"


def cfx_batches(db: Database, station: str, since: datetime, min_id: int = 0, extra_ids: Sequence[int] = (),
                limit: int = 200) -> list[BatchFacts]:
    """This station's batches of real parts (no replays) created at/after `since` with id >= min_id,
    plus `extra_ids`, oldest first, with their runs."""
    with db.session() as s:
        q = select(Batch).where(Batch.station == station, Batch.replay_of.is_(None))
        cond = (Batch.created_at >= since) & (Batch.id >= int(min_id))
        if extra_ids:
            cond = cond | Batch.id.in_([int(i) for i in extra_ids])
        batches = s.scalars(q.where(cond).order_by(Batch.id).limit(max(1, limit))).all()
        ids = [b.id for b in batches]
        runs: dict[int, list[RunFacts]] = {i: [] for i in ids}
        if ids:
            for r, serial in s.execute(select(DutRun, Dut.serial).join(Dut, Dut.id == DutRun.dut_id)
                                       .where(DutRun.batch_id.in_(ids)).order_by(DutRun.id)).all():
                runs[r.batch_id].append(RunFacts(run_id=r.id, slot=r.slot, serial=serial, state=r.state, verdict=r.verdict,
                                                 route_check=r.route_check, result_seq=r.result_seq,
                                                 started_at=r.started_at, ended_at=r.ended_at))
        out = []
        for b in batches:
            snap = b.config_snapshot or {}
            slots = tuple(str(x.get("name")) for x in snap.get("slots") or [] if isinstance(x, dict))
            cert = snap.get("certificate") or {}
            out.append(BatchFacts(
                batch_id=b.id, station=b.station, profile=b.profile, operator=b.operator, state=b.state,
                reason=b.reason or "", created_at=b.created_at, ended_at=b.ended_at, work_order=b.work_order or "",
                lot=b.lot or "", slots=slots, thermometer=_link(snap.get("thermometer")),
                thermometer_calibration=str(cert.get("reference_thermometer") or "") if isinstance(cert, dict) else "",
                runs=tuple(runs[b.id])))
        return out


def run_temperatures(db: Database, run_id: int) -> TempStats | None:
    """The temperatures of a run's stored segments (None: no segment stored)."""
    with db.session() as s:
        temps = sorted(float(t) for t in s.scalars(select(SegmentRow.temp_mean_c).where(SegmentRow.run_id == run_id)).all())
    if not temps:
        return None
    n = len(temps)
    median = temps[n // 2] if n % 2 else 0.5 * (temps[n // 2 - 1] + temps[n // 2])
    return TempStats(n=n, mean_c=sum(temps) / n, median_c=median, min_c=temps[0], max_c=temps[-1])


def cfx_prefix(station: str) -> str:
    """The idempotency-key prefix of one station's CFX messages (its own, in a shared database; a
    '/' in the name is escaped, so station "a" never reads station "a/b"'s messages)."""
    return "cfx/" + station.replace("%", "%25").replace("/", "%2F") + "/"


def cfx_queued_keys(db: Database, keys: Sequence[str]) -> set[str]:
    """Which of `keys` are in the outbox already (queued, delivered or not)."""
    if not keys:
        return set()
    with db.session() as s:
        return set(s.scalars(select(Outbox.idempotency_key).where(Outbox.idempotency_key.in_(list(keys)))).all())


def cfx_high_water(db: Database, station: str) -> int:
    """The highest verdict record (result_seq) whose UnitsTested this station queued (0: none)."""
    with db.session() as s:
        keys = s.scalars(select(Outbox.idempotency_key).where(
            Outbox.topic == CFX_TOPIC, Outbox.idempotency_key.startswith(cfx_prefix(station) + "units-tested/", autoescape=True),
        ).order_by(Outbox.id.desc()).limit(50)).all()
    seqs = [int(k.rsplit("/", 1)[1]) for k in keys if k.rsplit("/", 1)[1].isdigit()]
    return max(seqs, default=0)


def cfx_head(db: Database, station: str, limit: int = 20) -> list[dict[str, object]]:
    """This station's undelivered CFX messages, in the order they were queued (id), due or not:
    the sender stops at the first one that is not due or fails, so none overtakes another."""
    with db.session() as s:
        rows = s.scalars(select(Outbox).where(
            Outbox.topic == CFX_TOPIC, Outbox.delivered_at.is_(None),
            Outbox.idempotency_key.startswith(cfx_prefix(station), autoescape=True),
        ).order_by(Outbox.id).limit(max(1, limit))).all()
        return [{"id": o.id, "idempotency_key": o.idempotency_key, "payload": o.payload, "attempts": o.attempts,
                 "next_attempt_at": o.next_attempt_at} for o in rows]


def cfx_counts(db: Database, station: str) -> tuple[int, int]:
    """(delivered, pending) CFX messages of this station."""
    with db.session() as s:
        base = select(func.count()).select_from(Outbox).where(
            Outbox.topic == CFX_TOPIC, Outbox.idempotency_key.startswith(cfx_prefix(station), autoescape=True))
        delivered = int(s.scalar(base.where(Outbox.delivered_at.is_not(None))) or 0)
        pending = int(s.scalar(base.where(Outbox.delivered_at.is_(None))) or 0)
        return delivered, pending


__all__ = ["CFX_TOPIC", "RunFacts", "BatchFacts", "TempStats", "cfx_batches", "run_temperatures", "cfx_prefix",
           "cfx_queued_keys", "cfx_high_water", "cfx_head", "cfx_counts"]
