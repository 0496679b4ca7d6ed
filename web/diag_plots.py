"""Model diagnostics of stored runs for the web page: cached reports, their JSON and PNG plots.

A diagnosis of a 15-hour log takes seconds to tens of seconds (every candidate is fitted with
blocked K-fold held-out validation), so reports are cached per (run, added effects) in a small
LRU, and concurrent requests for the same key wait for one computation instead of repeating it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from station.diagnostics.effects import REGISTRY, get_effect
from station.diagnostics.plots import PLOTS, render_png
from station.diagnostics.ranking import DiagnosisReport, diagnose
from station.logfile import DutLog

CACHE_SIZE = 8


class DiagnosisCache:
    """LRU of DiagnosisReport by (run_id, effects added, in order)."""

    def __init__(self, size: int = CACHE_SIZE) -> None:
        self.size = size
        self._reports: OrderedDict[tuple, DiagnosisReport] = OrderedDict()
        self._locks: dict[tuple, threading.Lock] = {}
        self._guard = threading.Lock()

    def get(self, run_id: int, add: tuple[str, ...], log_fn) -> DiagnosisReport | None:
        """The report of a run with `add`; log_fn() -> DutLog | None loads the run's log."""
        key = (int(run_id), tuple(add))
        with self._guard:
            rep = self._reports.get(key)
            if rep is not None:
                self._reports.move_to_end(key)
                return rep
            lock = self._locks.setdefault(key, threading.Lock())
        with lock:
            with self._guard:
                rep = self._reports.get(key)
            if rep is not None:
                return rep
            log: DutLog | None = log_fn()
            if log is None:
                return None
            rep = diagnose([log], add=list(add))
            with self._guard:
                self._reports[key] = rep
                self._reports.move_to_end(key)
                while len(self._reports) > self.size:
                    self._reports.popitem(last=False)
                self._locks.pop(key, None)
            return rep


def check_effects(add: list[str]) -> tuple[str, ...]:
    """Validated, de-duplicated effect names (StationError names an unknown one)."""
    out = tuple(dict.fromkeys(a.strip() for a in add if a.strip()))
    for a in out:
        get_effect(a)
    return out


def report_json(rep: DiagnosisReport) -> dict:
    doc = rep.to_json()
    doc["plots"] = list(PLOTS)
    doc["library"] = [REGISTRY[n].describe() for n in REGISTRY]
    return doc


def plot_png(rep: DiagnosisReport, name: str) -> bytes:
    return render_png(rep, name, 0)


__all__ = ["DiagnosisCache", "check_effects", "report_json", "plot_png", "PLOTS"]
