"""The MES's route check, asked (design 5.4): one HTTP call per DUT before its run is made.

The rules (what to ask, how an answer reads, what the site's policy does with no answer) are
station/decisions/route_check.py's; this module makes the call with httpx, times it, and audits
it: every call leaves an audit row `route.check` (who asked about which serial, the outcome, the
MES's words, the HTTP status, how long it took), whatever the outcome, so "why was this part not
tested?" and "was this part tested without the MES's yes?" are answered from the database.

Called by station/daemon/slots.py once a board's identity and its label are known, before the
run is made and before its stream starts: a refused part never streams, so it never heats in the
station's data and never counts as an attempt of its serial.
"""

from __future__ import annotations

import asyncio
import logging
import time

import httpx

from db import repository as repo
from db.database import Database
from station.config import RouteCheck
from station.decisions.route_check import RouteAnswer, RoutePart, no_answer, read_answer, request_for

log = logging.getLogger(__name__)


class RouteGate:
    """Asks the MES configured in [mes.route_check] about one part at a time (concurrently for the
    slots of a batch: each call has its own timeout)."""

    def __init__(self, cfg: RouteCheck, station: str, db: Database | None) -> None:
        self.cfg = cfg
        self.station = station
        self.db = db

    def part(self, serial: str, slot: str, label_serial: str | None, work_order: str = "", part_number: str = "",
             lot: str = "") -> RoutePart:
        return RoutePart(serial=serial, slot=slot, operation=self.cfg.operation, station=self.station,
                         label_serial=label_serial or "", work_order=work_order, part_number=part_number, lot=lot)

    async def ask(self, part: RoutePart, batch_id: int) -> RouteAnswer:
        """The MES's answer for `part` (never raises: a failure is an `unanswered` answer), audited."""
        started = time.monotonic()
        try:
            req = request_for(self.cfg.url, self.cfg.method, part)
            async with httpx.AsyncClient(timeout=self.cfg.timeout_s, follow_redirects=False) as client:
                # the whole call within timeout_s: httpx's own timeout is per read, a trickling MES
                # would hold the slot for ever
                resp = await asyncio.wait_for(
                    client.request(req.method, req.url, json=req.json_body,
                                   headers={"User-Agent": "thermal-cal-station", **self.cfg.headers}),
                    timeout=self.cfg.timeout_s)
            answer = read_answer(resp.status_code, resp.content, allowed_field=self.cfg.allowed_field,
                                 reason_field=self.cfg.reason_field, refuse_statuses=self.cfg.refuse_statuses,
                                 elapsed_s=time.monotonic() - started)
        except (asyncio.TimeoutError, TimeoutError):
            answer = no_answer(f"no answer within {self.cfg.timeout_s:g} s", time.monotonic() - started)
        except (httpx.HTTPError, ValueError) as exc:
            answer = no_answer(f"{type(exc).__name__}: {exc}", time.monotonic() - started)
        log.info("batch %d slot %s: MES route check of %s: %s %s", batch_id, part.slot, part.serial,
                 answer.outcome, answer.reason)
        await asyncio.to_thread(self._audit, part, answer, batch_id)
        return answer

    def _audit(self, part: RoutePart, answer: RouteAnswer, batch_id: int) -> None:
        """route.check in the audit trail; logged loudly, never raised (the answer still holds)."""
        if self.db is None:
            return
        try:
            repo.audit_append(self.db, "station", "route.check", f"batch {batch_id} slot {part.slot}",
                              {"serial": part.serial, "label_serial": part.label_serial,
                               "operation": part.operation, "url": _no_credentials(self.cfg.url),
                               "method": self.cfg.method, "policy": self.cfg.when_unanswered, **answer.to_json()})
        except Exception:  # noqa: BLE001
            log.critical("audit: could not record the route check of %s in batch %d", part.serial, batch_id,
                         exc_info=True)


def _no_credentials(url: str) -> str:
    """The URL as the audit keeps it: no user:password@."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        return url
    host, slash, path = rest.partition("/")
    return f"{scheme}://{host.rpartition('@')[2]}{slash}{path}"
