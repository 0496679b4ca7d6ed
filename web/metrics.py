"""GET /metrics: the station's live figures in the Prometheus text format, for plant IT.

Every name, type, label and meaning is in docs/metrics.md; what this module does, and why:

- **One collector per app, its own registry.** `StationCollector` is a prometheus_client
  Collector registered in a `CollectorRegistry` of its own (never the process-global one): several
  apps (and stations) live in one test process, and a station must not export another's figures.
- **Read at scrape time.** Gauges (the batch's state, its DUTs per state and verdict, the lamp,
  the writer's queue, the active alarms, the intake's rate) are read from the daemon's facade when
  Prometheus asks, so a scrape costs nothing between scrapes and is never stale.
- **Counters from the event bus.** What must count every occurrence (samples received per slot,
  verdicts, batches started and ended, alarms raised, lamp on-time) is tallied by `EventTally`
  from the station's events as they happen: a batch that starts and ends between two scrapes is
  still counted, which a figure read at scrape time (the daemon keeps only the running and the
  last ended batch) could not promise. The tally runs while the web app runs (its lifespan).
- **Who may read.** A scraper whose TCP peer address is in `[metrics] allow` needs no token; anyone
  else needs a valid token of role admin or mes (web/auth.py). The peer is the connection's
  (request.client), never X-Forwarded-For: a header is what the client says, and any client can
  say it is 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import ipaddress
import time
from collections.abc import AsyncIterator, Iterable, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field

from fastapi import APIRouter, FastAPI, HTTPException, Request, status
from fastapi.responses import Response
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily
from prometheus_client.exposition import choose_encoder
from prometheus_client.registry import Collector, CollectorRegistry
from prometheus_client.metrics_core import Metric

from contracts.events import Alarm, BatchStateChanged, DutVerdict, Event, EventBus, LampChanged, SamplesReceived
from station.config import SlotConfig, StationConfig
from station.daemon.states import TERMINAL, TRANSITIONS
from station.daemon.supervisor import Station
from station.decisions.judging import VERDICTS
from web.auth import RESULTS, authenticate

IpNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address

BATCH_STATES: tuple[str, ...] = ("idle", *TRANSITIONS)  # idle: no batch since the daemon started
RUN_STATES: tuple[str, ...] = ("connecting", "identified", "running", "done", "faulted")  # DutRun.state
PENDING = "pending"  # a DUT of the batch without a verdict yet
ALARM_KINDS: tuple[str, ...] = ("overload", "lamp_trip", "lamp_relay", "storage", "slot_faulted")
BATCHES_REMEMBERED = 4096  # batch numbers the tally remembers to count each batch's start once
TALLY_QUEUE_EVENTS = 20_000  # the tally's bus queue (lossy like the page's: a stalled tally never stalls the daemon)
# headers a proxy adds (or a client claims): with one, the peer address is no proof of where the
# request comes from (MetricsAccess.check)
FORWARDING_HEADERS = ("x-forwarded-for", "forwarded", "x-real-ip", "x-forwarded-host", "x-client-ip")


def link_kind(slot: SlotConfig) -> str:
    """The `link` label: the kind of a slot's board link (serial or can), not its port: a label
    must not change when a board is moved to another port."""
    return "serial" if slot.serial is not None else "can"


# ============================================================================ access
def parse_networks(cidrs: Iterable[str]) -> tuple[IpNetwork, ...]:
    """The `[metrics] allow` list as networks (station/config.py has validated each entry)."""
    return tuple(ipaddress.ip_network(c, strict=True) for c in cidrs)


def peer_address(request: Request) -> IpAddress | None:
    """The TCP peer of the request (None: unknown, e.g. a Unix socket). An IPv4 address a dual-stack
    socket reports as IPv4-mapped IPv6 (::ffff:10.1.2.3) is taken as the IPv4 address it is."""
    client = request.client
    if client is None or not client.host:
        return None
    try:
        addr = ipaddress.ip_address(client.host.split("%", 1)[0])  # an IPv6 zone id is no part of the address
    except ValueError:
        return None
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return addr.ipv4_mapped
    return addr


@dataclass(frozen=True)
class MetricsAccess:
    """Who may scrape without a token (module doc)."""

    allow: tuple[IpNetwork, ...]

    @classmethod
    def from_config(cls, config: StationConfig | None) -> "MetricsAccess":
        """The config's `[metrics] allow`; a station-shaped test double without a config: loopback."""
        cidrs: Sequence[str] = config.metrics.allow if config is not None else ("127.0.0.1/32", "::1/128")
        return cls(parse_networks(cidrs))

    def allows(self, addr: IpAddress | None) -> bool:
        return addr is not None and any(addr.version == net.version and addr in net for net in self.allow)

    def check(self, request: Request) -> None:
        """Return if the request may read /metrics, else raise: 403 for a peer outside the list
        without a token and for a token whose role may not read it; 401 (the API's answer, with
        WWW-Authenticate) for a malformed or unknown token.

        A request carrying a forwarding header is never let in by its address: uvicorn (its
        default proxy_headers) rewrites request.client from X-Forwarded-For when the peer is
        127.0.0.1, so a process on the station PC could name itself an allowed address, and a
        reverse proxy on the PC makes every client look local. Through a proxy: a token."""
        addr = peer_address(request)
        forwarded = any(h in request.headers for h in FORWARDING_HEADERS)
        if self.allows(addr) and not forwarded:
            return
        if not request.headers.get("authorization"):
            why = ("came through a proxy (a forwarding header)" if forwarded
                   else f"{addr or 'an unknown address'} is not in [metrics] allow")
            raise HTTPException(status_code=status.HTTP_403_FORBIDDEN,
                                detail=f"/metrics: the request {why}; send an admin or mes token")
        principal = authenticate(request)  # 401 for a malformed or unknown token
        if principal.role not in RESULTS:
            raise HTTPException(status_code=status.HTTP_403_FORBIDDEN,
                                detail=f"/metrics: role '{principal.role}' may not read it; needs admin or mes")


# ============================================================================ counters from events
@dataclass
class EventTally:
    """Counters of the station's events since the web app started (module doc: why events).

    `lamp_on_since_s` is the wall time (time.time) the lamp was last switched on while it is on;
    the lamp's on-time is wall time, what the lamp and the plate live through."""

    samples_by_slot: dict[str, int] = field(default_factory=dict)
    verdicts: dict[str, int] = field(default_factory=dict)
    batches_started: int = 0
    batches_ended: dict[str, int] = field(default_factory=dict)
    alarms: dict[str, int] = field(default_factory=dict)  # severity -> alarms raised
    lamp_on_total_s: float = 0.0  # closed on-periods
    lamp_on_since_s: float | None = None
    lamp_switched_on: int = 0
    events_dropped: int = 0  # events the tally's queue lost (it fell this far behind: the counters undercount)
    _batches_seen: set[int] = field(default_factory=set)
    _task: asyncio.Task[None] | None = None
    _queue: asyncio.Queue[Event] | None = None
    _bus: EventBus | None = None

    def note(self, event: Event) -> None:
        """Count one event (the drain task calls this; a test may too)."""
        if isinstance(event, SamplesReceived):
            self.samples_by_slot[event.slot] = self.samples_by_slot.get(event.slot, 0) + len(event.block)
        elif isinstance(event, DutVerdict):
            verdict = str(event.verdict.get("verdict") or "error")
            self.verdicts[verdict] = self.verdicts.get(verdict, 0) + 1
        elif isinstance(event, BatchStateChanged):
            # a batch's first transition (created -> connecting) is its start: the event carries the
            # coarse state only ("running" for most), so a batch is started when first heard of
            if event.batch_id not in self._batches_seen:
                self._batches_seen.add(event.batch_id)
                self.batches_started += 1
                if len(self._batches_seen) > BATCHES_REMEMBERED:  # batch numbers grow: forget the oldest
                    self._batches_seen.discard(min(self._batches_seen))
            if event.state in TERMINAL:
                self.batches_ended[event.state] = self.batches_ended.get(event.state, 0) + 1
        elif isinstance(event, LampChanged):
            if event.on and self.lamp_on_since_s is None:  # set_lamp(True) again while on: one period
                self.lamp_on_since_s = event.wall_time
                self.lamp_switched_on += 1
            elif not event.on and self.lamp_on_since_s is not None:
                self.lamp_on_total_s += max(0.0, event.wall_time - self.lamp_on_since_s)
                self.lamp_on_since_s = None
        elif isinstance(event, Alarm):
            self.alarms[event.severity] = self.alarms.get(event.severity, 0) + 1

    def lamp_on_s(self, now_s: float) -> float:
        """Wall seconds the lamp was on since the tally began, the open period up to now included."""
        open_s = max(0.0, now_s - self.lamp_on_since_s) if self.lamp_on_since_s is not None else 0.0
        return self.lamp_on_total_s + open_s

    def start(self, bus: EventBus) -> None:
        if self._task is not None:
            return
        self._bus = bus
        self._queue = q = bus.subscribe(maxsize=TALLY_QUEUE_EVENTS, drop=True)
        self._task = asyncio.get_running_loop().create_task(self._drain(q), name="metrics-tally")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if self._bus is not None and self._queue is not None:
            self._bus.unsubscribe(self._queue)
        if task is not None:
            task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                pass

    async def _drain(self, q: asyncio.Queue[Event]) -> None:
        while True:
            event = await q.get()
            if q.qsize() >= TALLY_QUEUE_EVENTS - 1:  # it was full: the bus may have dropped the oldest
                self.events_dropped += 1
            self.note(event)
            while not q.empty():  # what arrived meanwhile, without a wake-up per event
                self.note(q.get_nowait())


# ============================================================================ the collector
def _gauge(name: str, doc: str, value: float, unit: str = "") -> GaugeMetricFamily:
    return GaugeMetricFamily(name, doc, value=value, unit=unit)


class StationCollector(Collector):
    """The station's figures at scrape time (module doc). `station` is the daemon's facade; a
    station-shaped test double that is not one yields only station_info."""

    def __init__(self, station: object, tally: EventTally, version: str) -> None:
        self.station = station
        self.tally = tally
        self.version = version

    def collect(self) -> Iterable[Metric]:
        st = self.station
        config = getattr(st, "config", None)
        name = config.name if isinstance(config, StationConfig) else ""
        info = InfoMetricFamily("station", "the station's name and software version")
        info.add_metric([], {"name": name, "version": self.version})
        yield info
        if not isinstance(st, Station):
            return
        yield from self._batch(st)
        yield from self._samples(st)
        yield from self._writer(st)
        yield from self._lamp(st)
        yield from self._alarms(st)

    # ------------------------------------------------------------------ batch and DUTs
    def _batch(self, st: Station) -> Iterable[Metric]:
        running = st.running_batch()
        ids = st.batch_ids()
        current = running if running is not None else (ids[-1] if ids else None)
        seq = st.batches.get(current) if current is not None else None
        state = seq.state if seq is not None else "idle"
        g = GaugeMetricFamily("station_batch_state", "1 for the state the current batch (the running one, "
                              "else the last ended) is in, 0 for the others; idle: no batch yet", labels=["state"])
        for s in BATCH_STATES:
            g.add_metric([s], 1.0 if s == state else 0.0)
        yield g
        yield _gauge("station_batch_id", "number of the current batch (0: none yet)", float(current or 0))
        yield _gauge("station_batch_running", "1 while a batch runs (the lamp and the plate are in use)",
                     1.0 if running is not None else 0.0)
        by_state = {s: 0 for s in RUN_STATES}
        by_verdict = {v: 0 for v in (*VERDICTS, PENDING)}
        if seq is not None:
            for d in seq.duts:
                by_state[d.state] = by_state.get(d.state, 0) + 1
                v = str((d.verdict or {}).get("verdict") or PENDING)
                by_verdict[v] = by_verdict.get(v, 0) + 1
        g = GaugeMetricFamily("station_batch_duts", "DUTs of the current batch per run state", labels=["state"])
        for s, n in by_state.items():
            g.add_metric([s], float(n))
        yield g
        g = GaugeMetricFamily("station_batch_duts_verdict", "DUTs of the current batch per final verdict "
                              "(pending: not judged yet)", labels=["verdict"])
        for v, n in by_verdict.items():
            g.add_metric([v], float(n))
        yield g
        t = self.tally
        c = CounterMetricFamily("station_duts_judged", "DUTs given a final verdict since the web app started",
                                labels=["verdict"])
        for v in (*VERDICTS, *sorted(set(t.verdicts) - set(VERDICTS))):
            c.add_metric([v], float(t.verdicts.get(v, 0)))
        yield c
        yield CounterMetricFamily("station_batches_started", "batches started since the web app started",
                                  value=float(t.batches_started))
        c = CounterMetricFamily("station_batches_ended", "batches ended since the web app started, per end state",
                                labels=["state"])
        for s in TERMINAL:
            c.add_metric([s], float(t.batches_ended.get(s, 0)))
        yield c

    # ------------------------------------------------------------------ samples and links
    def _samples(self, st: Station) -> Iterable[Metric]:
        slots = [rt.cfg for rt in st.slots.values()]
        received = CounterMetricFamily("station_samples_received", "samples the station took in from each slot's "
                                       "board since the web app started", labels=["slot", "link"])
        for cfg in slots:
            received.add_metric([cfg.name, link_kind(cfg)], float(self.tally.samples_by_slot.get(cfg.name, 0)))
        yield received
        lost = CounterMetricFamily("station_samples_lost", "samples missing from each slot's stream since its link "
                                   "was opened: cause station = lost to the station's own backlog, link = the "
                                   "board's or cable's", labels=["slot", "link", "cause"])
        frames = CounterMetricFamily("station_link_frames", "frames each slot's link received since it was opened, "
                                     "per result", labels=["slot", "link", "result"])
        for cfg in slots:
            stats = st.bank.link_stats(cfg.name)
            if stats is None:  # no driver: the link is closed (faulted, not connected)
                continue
            kind = link_kind(cfg)
            station_lost = stats.get("samples_lost_station", 0)
            lost.add_metric([cfg.name, kind, "station"], float(station_lost))
            lost.add_metric([cfg.name, kind, "link"], float(max(0, stats.get("samples_lost", 0) - station_lost)))
            for result, key in (("ok", "frames_ok"), ("bad_checksum", "frames_bad_checksum"),
                                ("malformed", "frames_malformed")):
                frames.add_metric([cfg.name, kind, result], float(stats.get(key, 0)))
        yield lost
        yield frames
        state = st.bank.monitor.state(time.monotonic())
        yield _gauge("station_intake_samples_per_second", "samples per second the station took in over its last "
                     "measuring window (all slots)", float(state.intake_samples_per_s or 0.0))
        yield _gauge("station_intake_capacity_samples_per_second", "samples per second this PC can follow "
                     "(measured CPU cost per sample)", float(state.capacity_samples_per_s or 0.0))
        yield _gauge("station_intake_behind_seconds", "the most the station runs behind any board link "
                     "(wall seconds of samples waiting)", float(state.behind_s))
        yield _gauge("station_process_cpu_share", "the station process's CPU seconds per wall second lately "
                     "(0.85 or more: saturated)", float(state.cpu_share or 0.0))

    # ------------------------------------------------------------------ database writer
    def _writer(self, st: Station) -> Iterable[Metric]:
        w = st.writer
        yield _gauge("station_writer_up", "1 while the database writer runs (0 before start and after close)",
                     0.0 if w is None else 1.0)
        if w is None:
            return
        yield _gauge("station_writer_queue_depth", "events handed to the writer and not yet in a transaction",
                     float(w.backlog))
        yield _gauge("station_writer_journal_events", "events held in the journal, waiting for the database",
                     float(w.waiting))
        failing_since = w.failing_since
        yield _gauge("station_writer_failing", "1 while the database does not take the writer's commits",
                     0.0 if w.failing is None else 1.0)
        yield _gauge("station_writer_failing_seconds", "how long the database has not taken commits (0: it does)",
                     max(0.0, time.time() - failing_since) if w.failing is not None and failing_since else 0.0)
        s = w.stats
        for name, doc, value in (
            ("station_writer_events_submitted", "events handed to the writer", s["submitted"]),
            ("station_writer_events_committed", "events committed to the database", s["committed_events"]),
            ("station_writer_samples_committed", "samples committed to the database", s["committed_samples"]),
            ("station_writer_commits", "database transactions committed", s["commits"]),
            ("station_writer_events_dropped", "events the database refused for themselves (dropped, logged)",
             s["dropped_events"]),
            ("station_writer_storage_failures", "commits that failed for storage (disk, I/O, lost connection)",
             s["storage_failures"]),
        ):
            yield CounterMetricFamily(name, f"{doc}, since the writer started", value=float(value))

    # ------------------------------------------------------------------ lamp
    def _lamp(self, st: Station) -> Iterable[Metric]:
        lamp = st.lamp
        yield CounterMetricFamily("station_lamp_on_seconds", "wall seconds the lamp was commanded on since the web "
                                  "app started (the current on-period included)",
                                  value=self.tally.lamp_on_s(time.time()), unit="seconds")
        yield CounterMetricFamily("station_lamp_switched_on", "times the lamp was switched on since the web app "
                                  "started", value=float(self.tally.lamp_switched_on))
        yield _gauge("station_lamp_on", "1 while the station commands the lamp on",
                     1.0 if lamp is not None and lamp.is_on else 0.0)
        yield _gauge("station_lamp_on_plant_seconds", "plant seconds the lamp has been on in this on-period "
                     "(what the safety trip compares with limits.lamp_max_on_s)",
                     lamp.on_time_s() if lamp is not None else 0.0)

    # ------------------------------------------------------------------ alarms
    def _alarms(self, st: Station) -> Iterable[Metric]:
        lamp = st.lamp
        overload = st.bank.monitor.state(time.monotonic()).alarm
        faulted = sum(1 for s in st.slots_status() if s.get("state") == "faulted")
        active = {
            "overload": 1 if overload is not None else 0,
            "lamp_trip": 1 if lamp is not None and lamp.trip_reason is not None else 0,
            "lamp_relay": 1 if lamp is None or lamp.relay_error is not None else 0,
            "storage": 0 if st.storage_status() == "ok" else 1,
            "slot_faulted": faulted,
        }
        g = GaugeMetricFamily("station_alarms_active", "alarms up now, by kind (slot_faulted: faulted slots)",
                              labels=["kind"])
        for kind in ALARM_KINDS:
            g.add_metric([kind], float(active[kind]))
        yield g
        c = CounterMetricFamily("station_alarms", "alarm events raised since the web app started, by severity",
                                labels=["severity"])
        for sev in sorted({"critical", "error", "warning", "info", *self.tally.alarms}):
            c.add_metric([sev], float(self.tally.alarms.get(sev, 0)))
        yield c
        yield CounterMetricFamily("station_metrics_events_dropped", "times the metrics tally found its event queue "
                                  "full (its counters may undercount)", value=float(self.tally.events_dropped))


# ============================================================================ the route
def build_router(station: object, version: str) -> APIRouter:
    """GET /metrics with its collector, registry and access (read from the station's config now);
    the router's lifespan (merged into the app's by include_router) runs the event tally."""
    config = getattr(station, "config", None)
    access = MetricsAccess.from_config(config if isinstance(config, StationConfig) else None)
    tally = EventTally()
    registry = CollectorRegistry(auto_describe=False)
    registry.register(StationCollector(station, tally, version))
    bus = getattr(station, "bus", None)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if isinstance(bus, EventBus):
            tally.start(bus)
        try:
            yield
        finally:
            await tally.stop()

    router = APIRouter(lifespan=lifespan)

    # Not in the OpenAPI document: it is Prometheus's text format, not the JSON API, with an access
    # rule of its own (docs/metrics.md is its reference).
    @router.get("/metrics", include_in_schema=False)
    async def metrics(request: Request) -> Response:
        """The station's figures in the Prometheus text format (OpenMetrics when the scraper asks)."""
        access.check(request)
        encoder, content_type = choose_encoder(request.headers.get("accept", ""))
        return Response(encoder(registry), media_type=content_type, headers={"Cache-Control": "no-store"})

    return router


__all__ = ["build_router", "MetricsAccess", "EventTally", "StationCollector", "parse_networks", "peer_address"]
