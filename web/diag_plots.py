"""Model diagnostics of stored runs for the web page: cached reports, their JSON and PNG plots.

A diagnosis of a 15-hour log takes seconds to tens of seconds (every candidate is fitted with
blocked K-fold held-out validation) and a plot a few hundred ms, and any read token may ask for
any run with any added effects. So both are bounded work (24 distinct diagnoses at once, unbounded,
pushed /api/health p50 from 5 to 245 ms):

- reports and PNGs are cached per key in small LRUs (a repeat costs nothing);
- requests for a key being computed wait for that one computation instead of repeating it;
- at most `max_running` distinct keys are computed at once and at most `max_waiting` requests
  wait for them; beyond that the request is refused at once with `Busy` (the route answers 429
  Too Many Requests with Retry-After: load shedding, not a server fault), so the thread pool and the CPU stay free for the live station.

The plots of a report are rendered as soon as the report is computed, before the page asks for
them (it asks only once it has shown the ranking; rendering them then put them seconds behind it):
one background thread per cache renders them one at a time, in the page's order, into the PNG
cache. It is bounded like any request (BoundedCache.prefetch: it takes one of the plot slots, never
waits, and skips a plot that is cached, being rendered, or that finds every slot taken: the page's
own request renders that one), and it holds the plots of at most PRERENDER_REPORTS reports, the
newest first: a report the engineer has clicked past is dropped.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque
from typing import Any, Callable, Generic, Hashable, TypeVar

from station.diagnostics.effects import REGISTRY, get_effect
from station.diagnostics.plots import PLOTS, flag_words, orientation_names, render_png
from station.diagnostics.ranking import DiagnosisReport, diagnose
from contracts.logfile import DutLog

logger = logging.getLogger(__name__)

CACHE_SIZE = 8  # reports (each holds its log's fitted arrays: a few MB for a long run)
PNG_CACHE_SIZE = 48  # plots, ~50-150 KB each
MAX_RUNNING_DIAGNOSES = 1  # the daemon has the live station to run: one diagnosis at a time
MAX_RUNNING_PLOTS = 2
MAX_WAITING = 8
PRERENDER_REPORTS = 2  # reports whose plots wait to be rendered ahead of the page (newest first)
PRERENDER_IDLE_S = 30.0  # the render-ahead thread ends after this long without work
# The order the page shows the plots in (and the order they are rendered ahead): the staircase and
# the ranking, the views that show what is missing (a leftover's views that carry its structure move
# up to here), then the rest.
PAGE_PLOTS = ("staircase", "ranking", "residual_vs_temperature", "residual_vs_orientation", "residual_vs_time",
              "residual_vs_rate", "measured_vs_model", "residual_vs_acceleration", "allan_deviation")
assert sorted(PAGE_PLOTS) == sorted(PLOTS), "every plot has its place on the page"

T = TypeVar("T")


class Busy(Exception):
    """Too much of this work is already running or waiting; retry after `retry_after_s`."""

    def __init__(self, what: str, retry_after_s: int) -> None:
        super().__init__(f"{what}: the station is busy with other requests of this kind, retry in {retry_after_s} s")
        self.retry_after_s = retry_after_s


class _Flight:
    __slots__ = ("done", "value", "error")

    def __init__(self) -> None:
        self.done = threading.Event()
        self.value = None
        self.error: BaseException | None = None


class BoundedCache(Generic[T]):
    """Thread-safe LRU with single-flight computation and admission limits (see module doc).

    `get(key, compute)` returns the cached value, or waits for the running computation of `key`,
    or computes it (compute() -> value; None is returned and not cached; an exception is passed to
    every waiter and not cached). Raises Busy when the limits are reached."""

    def __init__(self, what: str, size: int, max_running: int, max_waiting: int = MAX_WAITING) -> None:
        self.what = what
        self.size = int(size)
        self.max_running = int(max_running)
        self.max_waiting = int(max_waiting)
        self._values: OrderedDict[Hashable, T] = OrderedDict()
        self._flights: dict[Hashable, _Flight] = {}
        self._waiting = 0
        self._guard = threading.Lock()
        self._last_s = 1.0  # duration of the last computation: the Retry-After estimate
        self.computed = 0
        self.refused = 0

    def __len__(self) -> int:
        return len(self._values)

    @property
    def running(self) -> int:
        return len(self._flights)

    def has(self, key: Hashable) -> bool:
        """Is `key` cached or being computed?"""
        with self._guard:
            return key in self._values or key in self._flights

    def _busy(self) -> Busy:
        self.refused += 1
        return Busy(self.what, max(1, math.ceil(self._last_s)))

    def get(self, key: Hashable, compute: Callable[[], T | None], *, store: bool = True) -> T | None:
        """store=False: bounded and shared like any other, but not kept (a value still changing)."""
        with self._guard:
            if key in self._values:
                self._values.move_to_end(key)
                return self._values[key]
            flight = self._flights.get(key)
            if flight is not None:
                if self._waiting >= self.max_waiting:
                    raise self._busy()
                self._waiting += 1
                mine = False
            else:
                if len(self._flights) >= self.max_running:
                    raise self._busy()
                flight = self._flights[key] = _Flight()
                mine = True
        if not mine:
            try:
                flight.done.wait()
            finally:
                with self._guard:
                    self._waiting -= 1
            if flight.error is not None:
                raise flight.error
            return flight.value
        return self._run(key, flight, compute, store)

    def prefetch(self, key: Hashable, compute: Callable[[], T | None]) -> bool:
        """Compute and keep `key`'s value ahead of any request, within the same limits, never waiting
        and never refused: False (nothing done) when it is cached, being computed, or every computing
        slot is taken. A request for it meanwhile waits for this computation like for any other."""
        with self._guard:
            if key in self._values or key in self._flights or len(self._flights) >= self.max_running:
                return False
            flight = self._flights[key] = _Flight()
        try:
            self._run(key, flight, compute, True)
        except Exception:  # noqa: BLE001 - passed to the requests that waited; a request of its own retries
            logger.warning("%s: computing %r ahead failed", self.what, key, exc_info=True)
        return True

    def _run(self, key: Hashable, flight: _Flight, compute: Callable[[], T | None], store: bool) -> T | None:
        t0 = time.monotonic()
        try:
            value = compute()
        except BaseException as exc:
            flight.error = exc
            raise
        else:
            flight.value = value
            return value
        finally:
            with self._guard:
                self._last_s = time.monotonic() - t0
                self.computed += 1
                if store and flight.error is None and flight.value is not None:
                    self._values[key] = flight.value
                    self._values.move_to_end(key)
                    while len(self._values) > self.size:
                        self._values.popitem(last=False)
                del self._flights[key]
            flight.done.set()


_Item = tuple[Hashable, Callable[[], "bytes | None"]]  # (PNG cache key, render)


class _RenderAhead:
    """One background thread that renders reports' plots into the PNG cache before they are asked
    for (module doc): jobs are (report key, [(png key, compute), ...]); the newest job goes first,
    at most `max_jobs` wait (the oldest is dropped), and the thread ends when idle."""

    def __init__(self, pngs: "BoundedCache[bytes]", max_jobs: int = PRERENDER_REPORTS,
                 idle_s: float = PRERENDER_IDLE_S) -> None:
        self.pngs = pngs
        self.max_jobs = int(max_jobs)
        self.idle_s = float(idle_s)
        self._jobs: deque[tuple[Hashable, deque[_Item]]] = deque()  # newest last
        self._cv = threading.Condition()
        self._thread: threading.Thread | None = None
        self.rendered = 0  # plots this thread rendered
        self.skipped = 0  # plots left to the page's own request (every slot taken)
        self.dropped = 0  # jobs dropped for newer ones

    def submit(self, job_key: Hashable, items: list[_Item]) -> None:
        if self.max_jobs <= 0 or not items:
            return
        with self._cv:
            self._jobs = deque(j for j in self._jobs if j[0] != job_key)
            self._jobs.append((job_key, deque(items)))
            while len(self._jobs) > self.max_jobs:
                self._jobs.popleft()
                self.dropped += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="diagnosis-plots-ahead", daemon=True)
                self._thread.start()
            self._cv.notify()

    @property
    def pending(self) -> int:
        with self._cv:
            return sum(len(items) for _, items in self._jobs)

    def _next(self) -> _Item | None:
        with self._cv:
            if not self._jobs:
                self._cv.wait(self.idle_s)
            if not self._jobs:
                self._thread = None
                return None
            job_key, items = self._jobs[-1]
            item = items.popleft()
            if not items:
                self._jobs.pop()
            return item

    def _loop(self) -> None:
        while True:
            item = self._next()
            if item is None:
                return
            key, compute = item
            if self.pngs.prefetch(key, compute):
                self.rendered += 1
            elif not self.pngs.has(key):
                self.skipped += 1


class DiagnosisCache:
    """Reports by (run_id, effects added, in order) and their plots by (run_id, effects, plot)."""

    def __init__(self, size: int = CACHE_SIZE, *, png_size: int = PNG_CACHE_SIZE,
                 max_running: int = MAX_RUNNING_DIAGNOSES, max_running_plots: int = MAX_RUNNING_PLOTS,
                 max_waiting: int = MAX_WAITING, prerender: int = PRERENDER_REPORTS) -> None:
        """prerender: reports whose plots are rendered ahead of the page's requests (0: none)."""
        self.reports: BoundedCache[DiagnosisReport] = BoundedCache("diagnosis", size, max_running, max_waiting)
        self.pngs: BoundedCache[bytes] = BoundedCache("diagnosis plot", png_size, max_running_plots, max_waiting)
        self.ahead = _RenderAhead(self.pngs, max_jobs=prerender)

    def get(self, run_id: int, add: tuple[str, ...], log_fn) -> DiagnosisReport | None:
        """The report of a run with `add`; log_fn() -> DutLog | None loads the run's log. A report
        computed here has its plots rendered ahead at once (module doc)."""

        def compute() -> DiagnosisReport | None:
            log: DutLog | None = log_fn()
            if log is None:
                return None
            rep = diagnose([log], add=list(add))
            self.render_ahead(run_id, add, rep)
            return rep

        return self.reports.get((int(run_id), tuple(add)), compute)

    def render_ahead(self, run_id: int, add: tuple[str, ...], rep: DiagnosisReport) -> None:
        """Queue every plot of `rep` for the render-ahead thread, in the page's order."""
        self.ahead.submit((int(run_id), tuple(add)),
                          [(self._png_key(run_id, add, name), _plot_job(rep, name)) for name in plot_order(rep)])

    @staticmethod
    def _png_key(run_id: int, add: tuple[str, ...], name: str) -> tuple[int, tuple[str, ...], str]:
        return (int(run_id), tuple(add), name)

    def png(self, run_id: int, add: tuple[str, ...], name: str, rep: DiagnosisReport) -> bytes:
        return self.pngs.get(self._png_key(run_id, add, name), _plot_job(rep, name))


def _plot_job(rep: DiagnosisReport, name: str) -> Callable[[], bytes]:
    return lambda: plot_png(rep, name)  # plot_png looked up when it runs (tests slow it down)


def _leftover(rep: DiagnosisReport) -> dict[str, Any]:
    """The report's leftover statement (station/diagnostics/leftover.py) when it has one, else {}."""
    lo = getattr(rep, "leftover", None)
    return lo if isinstance(lo, dict) else {}


def plot_order(rep: DiagnosisReport) -> list[str]:
    """The plots in the page's order (PAGE_PLOTS), the views that carry a leftover's structure
    moved up right after the staircase and the ranking."""
    carrying = [p for p in (_leftover(rep).get("carrying") or []) if p in PAGE_PLOTS]
    head = [p for p in PAGE_PLOTS[:2]]
    return head + [p for p in carrying if p not in head] + [p for p in PAGE_PLOTS if p not in head and p not in carrying]


def check_effects(add: list[str]) -> tuple[str, ...]:
    """Validated, de-duplicated effect names (StationError names an unknown one). Exact names, as
    the OpenAPI schema's enum says: an empty or padded `add=` is an error, not silently dropped."""
    out = tuple(dict.fromkeys(add))
    for a in out:
        get_effect(a)
    return out


def report_json(rep: DiagnosisReport) -> dict:
    """The report's JSON (`station diagnose --json`) with what the page needs beside it: the plots
    in the page's order, the effect library, the noise view per DUT, each ranking flag in words
    (`flags_text`), and each DUT's orientations named as the CLI names them."""
    doc = rep.to_json()
    doc["plots"] = plot_order(rep)
    doc["library"] = [REGISTRY[n].describe() for n in REGISTRY]
    for r in doc.get("ranking", []):
        r["flags_text"] = [flag_words(f) for f in r.get("flags", [])]
    doc["orientations"] = {d.serial: [{"label": str(lab), "name": name}
                                      for lab, name in zip(d.pos_labels, orientation_names(d))]
                           for d in rep.data}
    # is the residual at the sensor's own noise? (Allan deviation beside a static segment, ~30 ms)
    doc["noise"] = {d.serial: rep.noise(k) for k, d in enumerate(rep.data)}
    return doc


def plot_png(rep: DiagnosisReport, name: str) -> bytes:
    return render_png(rep, name, 0)


__all__ = ["BoundedCache", "Busy", "DiagnosisCache", "check_effects", "report_json", "plot_png", "plot_order",
           "PLOTS", "PAGE_PLOTS"]
