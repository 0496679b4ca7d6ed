"""The CFX worker the daemon runs when [cfx] is enabled (docs/cfx.md): it queues the CFX messages
of this station's batches in the durable outbox, then sends them to the broker in order.

Why two halves:
- queueing reads only what the database holds (a batch row and its runs, a verdict record with its
  results, the run's stored segments), woken by the event bus but never trusting an event's data:
  a message is made from what was stored and decided, once, under a stable key (insert-or-get),
  so a restart that reads everything again queues nothing twice. The order a batch's messages are
  queued in is the order the line hears them: CalibrationPerformed (the reference thermometer, first
  use), StationStateChanged (idle -> working), WorkStarted, one UnitsTested per verdict record,
  WorkCompleted and StationStateChanged (-> idle or down) once every run's verdict is queued (or
  `complete_after_s` after the batch ended with runs left unjudged).
- sending takes this station's undelivered messages in id order and stops at the first one that
  is not due or fails (retried with exponential backoff): none overtakes another, and an entry is
  marked delivered only after the broker ACCEPTED it. A resend (the broker took it but its answer
  was lost) carries the same UniqueID, which is how the line recognises it.
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Mapping
from datetime import datetime, timedelta, timezone
from typing import Any, Protocol

from contracts.events import BatchStateChanged, DutVerdict, EventBus, SlotStateChanged
from contracts.json_safe import finite_or_none
from db import queries_cfx as Q
from db.database import Database
from db.models import utcnow
from db.queries_mes import outbox_enqueue_new, outbox_mark_delivered, outbox_mark_failed, results_since
from station.aio import cancel_and_wait
from station.cfx import messages as M
from station.config import Cfx, StationConfig

log = logging.getLogger("station.cfx")

ENDED = ("finished", "failed", "aborted", "interrupted")


class Sender(Protocol):
    """What sends one envelope (station/cfx/amqp.py AmqpSender; a test double)."""

    async def send(self, envelope: M.Envelope) -> None: ...

    async def close(self) -> None: ...


def backoff_s(attempts: int, base_s: float, max_s: float) -> float:
    """Delay before the next try after `attempts` failures: base * 2^(n-1), capped, +-20 % jitter."""
    return float(min(max_s, base_s * 2.0 ** max(0, attempts - 1)) * random.uniform(0.8, 1.2))


def _dt(value: object) -> datetime | None:
    if isinstance(value, datetime):
        return value
    if isinstance(value, str) and value:
        return datetime.fromisoformat(value)
    return None


def _axis(thermal: object, ax: str, key: str) -> float | None:
    if not isinstance(thermal, Mapping):
        return None
    item = thermal.get(ax)
    return finite_or_none(item.get(key)) if isinstance(item, Mapping) else None


# Any: one record of db/queries_mes.py results_since (its JSON answer, values unchecked); read here
# field by field into the typed VerdictFacts, the only shape that goes on.
def verdict_facts(rec: Mapping[str, Any], run: Q.RunFacts | None) -> M.VerdictFacts:
    """A results_since record (and its run's times) as the builder's typed input."""
    thermal = rec.get("thermal")
    xyz = ("x", "y", "z")
    tdb = tuple(_axis(thermal, a, "tdb_mg_per_c") for a in xyz)
    tdsf = tuple(_axis(thermal, a, "tdsf_ppm_per_c") for a in xyz)
    return M.VerdictFacts(
        result_seq=int(rec["id"]), run_id=int(rec["run_id"]), batch_id=int(rec["batch_id"]), slot=str(rec["slot"]),
        serial=str(rec.get("serial") or ""), verdict=rec.get("verdict"), grade=rec.get("grade"), tray=rec.get("tray"),
        reason=str(rec.get("reason") or ""), judged_at=_dt(rec.get("judged_at") or rec.get("created_at")),
        started_at=run.started_at if run else None, ended_at=run.ended_at if run else _dt(rec.get("ended_at")),
        attempt=int(rec.get("attempt") or 0), revision=int(rec.get("revision") or 1), route_check=rec.get("route_check"),
        limits_name=rec.get("limits_name"), limits_version=rec.get("limits_version"),
        tdb_mg_per_c=(tdb[0], tdb[1], tdb[2]), tdsf_ppm_per_c=(tdsf[0], tdsf[1], tdsf[2]))


class CfxOutbox:
    """Queue and send this station's CFX messages (module doc). start()/stop() from the daemon."""

    def __init__(self, db: Database, bus: EventBus | None, config: StationConfig, sender: Sender | None = None) -> None:
        self.db = db
        self.bus = bus
        # the name this station's rows are stamped with (Database.station, config `name` when the daemon
        # opens it): its batches, its records, its outbox keys, in a database other stations may share
        self.station = db.station
        self.cfg: Cfx = config.cfx
        self.source = self.cfg.handle or M.default_handle(config.name)
        self.sender = sender
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._bus_task: asyncio.Task[None] | None = None
        self._high_water = 0  # highest verdict record (result_seq) whose UnitsTested is queued
        self._floor_id = 0  # the oldest batch whose end messages are not queued yet
        self._since = utcnow() - timedelta(hours=self.cfg.lookback_h)
        self.queued = 0
        self.delivered = 0
        self.failures = 0
        self.last_error = ""

    async def start(self) -> None:
        if self.sender is None:
            from station.cfx.amqp import AmqpSender  # proton only when CFX is on

            self.sender = AmqpSender(self.cfg.broker_url, self.cfg.address, timeout_s=self.cfg.timeout_s,
                                     subject_mode=self.cfg.subject, container_id=f"thermal-cal-station/{self.station}")
        try:
            self._high_water = await asyncio.to_thread(Q.cfx_high_water, self.db, self.station)
        except Exception as exc:  # noqa: BLE001 - then read every record again; queueing is idempotent
            log.warning("CFX: no high-water mark (%s); reading all verdict records", exc)
        self._task = asyncio.create_task(self._run(), name="cfx-outbox")
        if self.bus is not None:
            self._bus_task = asyncio.create_task(self._watch_bus(), name="cfx-outbox-bus")

    async def stop(self) -> None:
        for task in (self._bus_task, self._task):
            if not await cancel_and_wait(task):
                log.error("CFX outbox: a task did not stop within 5 s")
        if self.sender is not None:
            await self.sender.close()

    def wake(self) -> None:
        self._wake.set()

    async def _watch_bus(self) -> None:
        """Wake the worker when a batch changes state, a slot binds or a verdict is decided (the
        data itself is read from the database, once the writer has committed it)."""
        assert self.bus is not None
        q = self.bus.subscribe(maxsize=1000, drop=True)
        try:
            while True:
                ev = await q.get()
                if isinstance(ev, (BatchStateChanged, DutVerdict, SlotStateChanged)):
                    await asyncio.sleep(0.3)  # the db writer commits in batches
                    self.wake()
        finally:
            self.bus.unsubscribe(q)

    async def _run(self) -> None:
        while True:
            wait_s = self.cfg.poll_s
            try:
                self.queued += await asyncio.to_thread(self.enqueue_pass)
                wait_s = min(wait_s, await self.deliver_due())
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - the worker must outlive a db hiccup
                log.warning("CFX outbox pass failed: %s", exc)
            try:
                await asyncio.wait_for(self._wake.wait(), timeout=max(0.05, wait_s))
            except (asyncio.TimeoutError, TimeoutError):
                pass
            self._wake.clear()

    # ------------------------------------------------------------ queueing (sync, in a thread)

    def enqueue_pass(self) -> int:
        """Queue every message the stored data now calls for, in order. Returns how many were new."""
        records: list[Mapping[str, Any]] = []
        while True:
            page = results_since(self.db, max([self._high_water] + [int(r["id"]) for r in records]), 200, None, self.station)
            if not page:
                break
            records += page
        by_batch: dict[int, list[Mapping[str, Any]]] = {}
        for rec in records:
            by_batch.setdefault(int(rec["batch_id"]), []).append(rec)
        new_hw = max([self._high_water] + [int(r["id"]) for r in records])
        batches = Q.cfx_batches(self.db, self.station, self._since, self._floor_id, sorted(by_batch))
        now = utcnow()
        out: list[M.Outgoing] = []
        open_ids: list[int] = []
        for b in batches:
            if b.state == "created":
                open_ids.append(b.batch_id)
                continue
            cal = M.calibration_performed(b, self.source)
            out += ([cal] if cal else []) + [M.station_state_changed(b, self.source, True), M.work_started(b, self.source)]
            runs = {r.run_id: r for r in b.runs}
            for rec in by_batch.get(b.batch_id, []):
                run = runs.get(int(rec["run_id"]))
                out.append(M.units_tested(b, verdict_facts(rec, run), Q.run_temperatures(self.db, int(rec["run_id"])), self.source))
            # every run's latest verdict record queued (its result_seq at or below what was read)
            judged = all(r.result_seq is not None and r.result_seq <= new_hw for r in b.runs)
            late = b.ended_at is not None and (now - b.ended_at).total_seconds() >= self.cfg.complete_after_s
            if b.state in ENDED and b.ended_at is not None and (judged or late):
                out += [M.work_completed(b, self.source), M.station_state_changed(b, self.source, False)]
            else:
                open_ids.append(b.batch_id)
        added = 0
        queued = Q.cfx_queued_keys(self.db, [o.key for o in out])
        for o in out:
            if o.key in queued:
                continue
            queued.add(o.key)  # a calibration shared by two batches of this pass: once
            if outbox_enqueue_new(self.db, o.key, o.envelope, topic=Q.CFX_TOPIC)[1]:
                added += 1
                log.info("CFX: queued %s (%s)", o.envelope["MessageName"], o.key)
        self._high_water = new_hw
        if batches:
            newest = max(b.batch_id for b in batches)
            self._floor_id = min(open_ids, default=newest + 1)
        return added

    # ------------------------------------------------------------ sending

    async def deliver_due(self) -> float:
        """Send this station's messages in order until one is not due or fails. Returns the seconds
        until the head is due again (poll_s when nothing waits)."""
        assert self.sender is not None
        while True:
            head = await asyncio.to_thread(Q.cfx_head, self.db, self.station, 20)
            if not head:
                return self.cfg.poll_s
            for entry in head:
                due = entry["next_attempt_at"]
                assert isinstance(due, datetime)
                wait = (due - datetime.now(timezone.utc)).total_seconds()
                if wait > 0:
                    return min(self.cfg.poll_s, wait)
                payload = entry["payload"]
                assert isinstance(payload, dict)
                envelope: M.Envelope = payload  # type: ignore[assignment]  # stored as built (messages.Envelope)
                entry_id = int(str(entry["id"]))
                try:
                    await self.sender.send(envelope)
                except Exception as exc:  # noqa: BLE001 - any failure: retry this one later, nothing after it
                    attempts = int(str(entry["attempts"])) + 1
                    delay = backoff_s(attempts, self.cfg.base_delay_s, self.cfg.max_delay_s)
                    when = datetime.fromtimestamp(time.time() + delay, tz=timezone.utc)
                    await asyncio.to_thread(outbox_mark_failed, self.db, entry_id, str(exc)[:500], when)
                    self.failures += 1
                    self.last_error = str(exc)
                    log.warning("CFX: sending %s failed (%s), attempt %d, next in %.1f s", entry["idempotency_key"], exc,
                                attempts, delay)
                    return delay
                await asyncio.to_thread(outbox_mark_delivered, self.db, entry_id)
                self.delivered += 1
                log.debug("CFX: delivered %s", entry["idempotency_key"])


__all__ = ["CfxOutbox", "Sender", "backoff_s", "verdict_facts"]
