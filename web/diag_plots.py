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
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from typing import Callable, Generic, Hashable, TypeVar

from station.diagnostics.effects import REGISTRY, get_effect
from station.diagnostics.plots import PLOTS, render_png
from station.diagnostics.ranking import DiagnosisReport, diagnose
from contracts.logfile import DutLog

CACHE_SIZE = 8  # reports (each holds its log's fitted arrays: a few MB for a long run)
PNG_CACHE_SIZE = 48  # plots, ~50-150 KB each
MAX_RUNNING_DIAGNOSES = 1  # the daemon has the live station to run: one diagnosis at a time
MAX_RUNNING_PLOTS = 2
MAX_WAITING = 8

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


class DiagnosisCache:
    """Reports by (run_id, effects added, in order) and their plots by (run_id, effects, plot)."""

    def __init__(self, size: int = CACHE_SIZE, *, png_size: int = PNG_CACHE_SIZE,
                 max_running: int = MAX_RUNNING_DIAGNOSES, max_running_plots: int = MAX_RUNNING_PLOTS,
                 max_waiting: int = MAX_WAITING) -> None:
        self.reports: BoundedCache[DiagnosisReport] = BoundedCache("diagnosis", size, max_running, max_waiting)
        self.pngs: BoundedCache[bytes] = BoundedCache("diagnosis plot", png_size, max_running_plots, max_waiting)

    def get(self, run_id: int, add: tuple[str, ...], log_fn) -> DiagnosisReport | None:
        """The report of a run with `add`; log_fn() -> DutLog | None loads the run's log."""

        def compute() -> DiagnosisReport | None:
            log: DutLog | None = log_fn()
            return None if log is None else diagnose([log], add=list(add))

        return self.reports.get((int(run_id), tuple(add)), compute)

    def png(self, run_id: int, add: tuple[str, ...], name: str, rep: DiagnosisReport) -> bytes:
        return self.pngs.get((int(run_id), tuple(add), name), lambda: plot_png(rep, name))


def check_effects(add: list[str]) -> tuple[str, ...]:
    """Validated, de-duplicated effect names (StationError names an unknown one). Exact names, as
    the OpenAPI schema's enum says: an empty or padded `add=` is an error, not silently dropped."""
    out = tuple(dict.fromkeys(add))
    for a in out:
        get_effect(a)
    return out


def report_json(rep: DiagnosisReport) -> dict:
    doc = rep.to_json()
    doc["plots"] = list(PLOTS)
    doc["library"] = [REGISTRY[n].describe() for n in REGISTRY]
    # is the residual at the sensor's own noise? (Allan deviation beside a static segment, ~30 ms)
    doc["noise"] = {d.serial: rep.noise(k) for k, d in enumerate(rep.data)}
    return doc


def plot_png(rep: DiagnosisReport, name: str) -> bytes:
    return render_png(rep, name, 0)


__all__ = ["BoundedCache", "Busy", "DiagnosisCache", "check_effects", "report_json", "plot_png", "PLOTS"]
