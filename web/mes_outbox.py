"""Webhook delivery of the MES records, each a run's final verdict (design 8), with its results.

The worker copies every verdict record into the db outbox table (enqueue is idempotent on the
record's idempotency key; a superseding record has its own key and names the one it replaces in
`supersedes`, with `revision` N + 1), then POSTs each due entry to the configured URL with the key in an
`Idempotency-Key` header and in the payload. Failures (non-2xx, timeout, refused) are retried
with exponential backoff; the schedule lives in the table, so a restart resumes where it stopped.
The same result always carries the same key, so a retry after a lost reply is recognisable by the
MES as the same record, never a second one.
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from dataclasses import dataclass

import httpx

from contracts.events import DutVerdict
from contracts.trace import TRACE_FIELDS
from station.aio import cancel_and_wait
from station.config import StationConfig
from web.repo import WebRepository
from web.views import clean

log = logging.getLogger("station.web.mes")


@dataclass
class OutboxConfig:
    url: str
    timeout_s: float = 10.0
    base_delay_s: float = 2.0
    max_delay_s: float = 600.0
    poll_s: float = 2.0
    batch: int = 20
    station_name: str = "station"

    @classmethod
    def from_config(cls, config: StationConfig | None) -> "OutboxConfig | None":
        """The outbox of a station's [mes] section (None: no webhook configured)."""
        if not isinstance(config, StationConfig) or not config.mes.webhook_url:
            return None
        m = config.mes
        return cls(url=m.webhook_url, timeout_s=m.timeout_s, base_delay_s=m.base_delay_s, max_delay_s=m.max_delay_s,
                   poll_s=m.poll_s, batch=m.batch, station_name=config.name)


def backoff_s(attempts: int, base_s: float, max_s: float) -> float:
    """Delay before the next try after `attempts` failures: base * 2^(n-1), capped, +-20 % jitter."""
    delay = min(max_s, base_s * (2 ** max(0, attempts - 1)))
    return delay * random.uniform(0.8, 1.2)


def payload_of(result: dict, station_name: str) -> dict:
    """The webhook body of one feed record (db/repository.py results_since): the same data as the
    feed, so the MES gets the trace (work order, part, lot, label serial, operator) either way."""
    thermal = result.get("thermal") or None
    axes = thermal.get("axes") if isinstance(thermal, dict) and "axes" in thermal else thermal
    by_method = result.get("thermal_by_method") or {}
    return clean(
        {
            "idempotency_key": result["idempotency_key"],
            # the station that measured it: with one shared database, any station's worker may send it
            "station": result.get("station") or station_name,
            "result_id": result.get("id"),
            "serial": result.get("serial"),
            "run_id": result.get("run_id"),
            "batch_id": result.get("batch_id"),
            "slot": result.get("slot"),
            "created_at": result.get("created_at"),
            # a later verdict of the same run is a new record: revision N + 1, naming the key it replaces
            "revision": result.get("revision"),
            "supersedes": result.get("supersedes"),
            "thermal": axes,
            "streaming": by_method.get("streaming"),
            "offline": by_method.get("offline"),
            "sfem": result.get("sfem"),
            # what the batch was started for and who ran it (contracts/trace.py)
            **{k: result.get(k) for k in ("profile", "operator", "sensor", "label_serial", *TRACE_FIELDS)},
            # the MES's route check of the part (design 5.4): "unanswered" = tested without its yes
            **{k: result.get(k) for k in ("route_check", "route_reason")},
            # the station's decision: verdict pass/marginal/fail/error, grade (bin), tray,
            # plain-words reason, the serial's attempt number and the limits set it was judged by
            **{k: result.get(k) for k in ("verdict", "grade", "tray", "reason", "attempt", "limits_name",
                                          "limits_version")},
        }
    )


class MesOutbox:
    def __init__(self, repo: WebRepository, config: OutboxConfig, bus=None) -> None:
        self.repo = repo
        self.config = config
        self.bus = bus
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._bus_task: asyncio.Task | None = None
        self._high_water = 0  # highest result id already copied to the outbox (this process)
        self.delivered = 0
        self.failures = 0

    async def start(self) -> None:
        try:
            self._high_water = int(await asyncio.to_thread(self.repo.outbox_high_water))
        except Exception as exc:  # noqa: BLE001 - then scan everything; enqueue is idempotent
            log.warning("MES outbox: no high-water mark (%s); scanning all results", exc)
        self._client = httpx.AsyncClient(timeout=self.config.timeout_s, follow_redirects=False)
        self._task = asyncio.create_task(self._run(), name="mes-outbox")
        if self.bus is not None:
            self._bus_task = asyncio.create_task(self._watch_bus(), name="mes-outbox-bus")

    async def stop(self) -> None:
        for task in (self._bus_task, self._task):
            if not await cancel_and_wait(task):
                log.error("MES outbox: task %s did not stop within 5 s", task.get_name())
        await self._client.aclose()

    def wake(self) -> None:
        self._wake.set()

    async def _watch_bus(self) -> None:
        q = self.bus.subscribe(maxsize=1000, drop=True)
        try:
            while True:
                ev = await q.get()
                if isinstance(ev, DutVerdict):  # the only event that makes an MES record
                    # the db writer commits in batches; look again shortly after
                    await asyncio.sleep(0.2)
                    self.wake()
        finally:
            self.bus.unsubscribe(q)

    async def _run(self) -> None:
        while True:
            try:
                await self.run_once()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - the worker must outlive a db hiccup
                log.warning("MES outbox pass failed: %s", exc)
            try:
                await asyncio.wait_for(self._wake.wait(), timeout=self.config.poll_s)
            except (asyncio.TimeoutError, TimeoutError):
                pass
            self._wake.clear()

    async def enqueue_new(self) -> int:
        """Copy results not yet in the outbox; idempotent, so a restart re-scan adds nothing twice."""
        added = 0
        while True:
            rows = await asyncio.to_thread(self.repo.results_since, self._high_water, None, 200)
            if not rows:
                return added
            for r in rows:
                if await asyncio.to_thread(self.repo.outbox_enqueue, r["idempotency_key"], payload_of(r, self.config.station_name)):
                    added += 1
                self._high_water = max(self._high_water, int(r["id"]))

    async def run_once(self) -> int:
        """One pass: enqueue new results (unless the db writer already queues them in the result's
        own transaction), deliver every due entry. Returns deliveries made."""
        if not getattr(self.repo, "writes_outbox", False):
            await self.enqueue_new()
        done = 0
        due = await asyncio.to_thread(self.repo.outbox_due, time.time(), self.config.batch)
        for entry in due:
            if await self._deliver(entry):
                done += 1
        return done

    async def _deliver(self, entry: dict) -> bool:
        key = entry["idempotency_key"]
        payload = dict(entry["payload"])
        payload["idempotency_key"] = key
        try:
            resp = await self._client.post(
                self.config.url,
                json=payload,
                headers={"Idempotency-Key": key, "User-Agent": "thermal-cal-station"},
            )
            ok = 200 <= resp.status_code < 300
            error = "" if ok else f"HTTP {resp.status_code}"
        except httpx.HTTPError as exc:
            ok, error = False, f"{type(exc).__name__}: {exc}".strip()
        if ok:
            await asyncio.to_thread(self.repo.outbox_mark_delivered, entry["id"])
            self.delivered += 1
            log.info("MES: delivered %s", key)
            return True
        attempts = int(entry.get("attempts") or 0) + 1
        delay = backoff_s(attempts, self.config.base_delay_s, self.config.max_delay_s)
        await asyncio.to_thread(self.repo.outbox_mark_failed, entry["id"], error[:500], time.time() + delay)
        self.failures += 1
        log.warning("MES: delivery of %s failed (%s), attempt %d, next in %.1f s", key, error, attempts, delay)
        return False
