"""Yield and statistical process control over judged DUT runs (issue 13). Pure: plain dicts in
(the runs as db.repository.judged_runs gives them), typed dataclasses out; numpy only.

A parameter is one judged measurement, `measurement` or `measurement:axis` (e.g.
`tdb_mg_per_c:z`), taken from each run's verdict checks (station/decisions/verdicts.py). The checks also carry
the spec limits the run was judged by, so Cpk is always against the limits in force for that run's
product and version, never against a guess.

- Individuals chart (I-MR): centre = mean; sigma_within = MR-bar / d2 (d2 = 1.128 for moving
  ranges of two); limits mean ± 3 sigma_within (= ± 2.66 MR-bar); MR chart UCL = D4 MR-bar
  (D4 = 3.267). Points beyond the limits are flagged.
- Capability: Cpk = min(USL - mean, mean - LSL) / (3 sigma_within) (the short-term figure SPC uses),
  Ppk the same with the overall sample sigma. One-sided limits give the one side; none give None.
- Histogram with the spec limits; per-slot trend (mean per slot: a slot that reads high is a
  fixture or board-link problem, not a process shift).
- Yield per batch, per day (UTC) and per product (limits set): pass / judged.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable

import numpy as np

D2_MR2 = 1.128  # d2 for subgroups of 2 (moving range)
D4_MR2 = 3.267  # D4 for subgroups of 2
VERDICTS = ("pass", "marginal", "fail", "error")


@dataclass(frozen=True)
class Point:
    run_id: int
    batch_id: int
    station: str
    slot: str
    serial: str
    at: str | None  # judged at (ISO 8601)
    value: float
    low: float | None
    high: float | None
    verdict: str | None


@dataclass
class IChart:
    n: int
    mean: float | None
    mr_bar: float | None
    sigma_within: float | None
    ucl: float | None
    lcl: float | None
    mr_ucl: float | None
    moving_ranges: list[float] = field(default_factory=list)
    out_of_control: list[int] = field(default_factory=list)  # indices of points beyond the limits


@dataclass
class Capability:
    n: int
    low: float | None
    high: float | None
    mean: float | None
    sigma_within: float | None
    sigma_overall: float | None
    cpk: float | None
    ppk: float | None
    out_of_spec: int


@dataclass
class Histogram:
    edges: list[float]
    counts: list[int]


@dataclass
class SlotTrend:
    slot: str
    n: int
    mean: float
    values: list[float]


@dataclass
class SpcReport:
    parameter: str
    unit: str
    points: list[Point]
    chart: IChart
    capability: Capability
    histogram: Histogram
    slots: list[SlotTrend]

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class YieldRow:
    key: str
    judged: int
    passed: int
    marginal: int
    failed: int
    errors: int
    yield_pct: float | None


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


def parameter_of(check: dict) -> str:
    m = str(check.get("measurement") or "")
    return f"{m}:{check['axis']}" if check.get("axis") else m


def parameters(runs: Iterable[dict]) -> list[str]:
    """Every parameter with at least one numeric value, in first-seen order."""
    seen: dict[str, None] = {}
    for r in runs:
        for c in r.get("checks") or []:
            if isinstance(c, dict) and _finite(c.get("value")):
                seen.setdefault(parameter_of(c), None)
    return list(seen)


def series(runs: Iterable[dict], parameter: str) -> tuple[list[Point], str]:
    """The parameter's values in the order of the runs (judging time), with each run's limits."""
    points: list[Point] = []
    unit = ""
    for r in runs:
        for c in r.get("checks") or []:
            if isinstance(c, dict) and parameter_of(c) == parameter and _finite(c.get("value")):
                unit = unit or str(c.get("unit") or "")
                points.append(Point(int(r["run_id"]), int(r.get("batch_id") or 0), str(r.get("station") or ""),
                                    str(r.get("slot") or ""), str(r.get("serial") or ""), r.get("judged_at"),
                                    float(c["value"]),
                                    float(c["low"]) if _finite(c.get("low")) else None,
                                    float(c["high"]) if _finite(c.get("high")) else None, r.get("verdict")))
                break
    return points, unit


def individuals(values: list[float]) -> IChart:
    x = np.asarray(values, dtype=float)
    n = len(x)
    if n == 0:
        return IChart(0, None, None, None, None, None, None)
    mean = float(x.mean())
    if n < 2:
        return IChart(n, mean, None, None, None, None, None)
    mr = np.abs(np.diff(x))
    mr_bar = float(mr.mean())
    sigma = mr_bar / D2_MR2
    ucl, lcl = mean + 3 * sigma, mean - 3 * sigma
    ooc = [i for i, v in enumerate(x) if v > ucl or v < lcl] if sigma > 0 else []
    return IChart(n, mean, mr_bar, sigma, ucl, lcl, D4_MR2 * mr_bar, [float(v) for v in mr], ooc)


def _one_sided(mean: float, sigma: float | None, low: float | None, high: float | None) -> float | None:
    if sigma is None or sigma <= 0 or (low is None and high is None):
        return None
    sides = []
    if high is not None:
        sides.append((high - mean) / (3 * sigma))
    if low is not None:
        sides.append((mean - low) / (3 * sigma))
    return float(min(sides))


def capability(values: list[float], low: float | None, high: float | None, sigma_within: float | None) -> Capability:
    x = np.asarray(values, dtype=float)
    n = len(x)
    out_of_spec = int(sum(1 for v in x if (high is not None and v > high) or (low is not None and v < low)))
    if n == 0:
        return Capability(0, low, high, None, None, None, None, None, 0)
    mean = float(x.mean())
    overall = float(x.std(ddof=1)) if n > 1 else None
    return Capability(n, low, high, mean, sigma_within, overall, _one_sided(mean, sigma_within, low, high),
                      _one_sided(mean, overall, low, high), out_of_spec)


def histogram(values: list[float], low: float | None = None, high: float | None = None, bins: int = 12) -> Histogram:
    """Bins spanning the data and the spec limits (so the limits are on the plot)."""
    x = np.asarray(values, dtype=float)
    if len(x) == 0:
        return Histogram([], [])
    lo = min([float(x.min())] + ([low] if low is not None else []))
    hi = max([float(x.max())] + ([high] if high is not None else []))
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    counts, edges = np.histogram(x, bins=bins, range=(lo, hi))
    return Histogram([float(e) for e in edges], [int(c) for c in counts])


def slot_trend(points: list[Point]) -> list[SlotTrend]:
    by: dict[str, list[float]] = {}
    for p in points:
        by.setdefault(p.slot, []).append(p.value)
    return [SlotTrend(s, len(v), float(np.mean(v)), v) for s, v in sorted(by.items())]


def spc_report(runs: list[dict], parameter: str, bins: int = 12) -> SpcReport:
    points, unit = series(runs, parameter)
    values = [p.value for p in points]
    chart = individuals(values)
    # the limits of the newest run: a limits change shows as a new line from then on in the CSV
    low = points[-1].low if points else None
    high = points[-1].high if points else None
    return SpcReport(parameter, unit, points, chart, capability(values, low, high, chart.sigma_within),
                     histogram(values, low, high, bins), slot_trend(points))


def _day(iso: str | None) -> str:
    return (iso or "")[:10] or "unknown"


def yields(runs: Iterable[dict], by: str) -> list[YieldRow]:
    """Yield per `batch`, `day` (UTC, of judging) or `product` (limits set): pass / judged runs.
    Every judged attempt counts (a retest is a second run), as the station tested it."""
    key_of = {
        "batch": lambda r: str(r.get("batch_id")),
        "day": lambda r: _day(r.get("judged_at")),
        "product": lambda r: str(r.get("limits_name") or "unknown"),
        "station": lambda r: str(r.get("station") or "unknown"),
    }[by]
    groups: dict[str, dict[str, int]] = {}
    for r in runs:
        v = r.get("verdict")
        if v not in VERDICTS:
            continue
        g = groups.setdefault(key_of(r), {k: 0 for k in VERDICTS})
        g[v] += 1
    out = []
    for key, g in groups.items():
        judged = sum(g.values())
        out.append(YieldRow(key, judged, g["pass"], g["marginal"], g["fail"], g["error"],
                            100.0 * g["pass"] / judged if judged else None))
    return out


CSV_COLUMNS = ("run_id", "batch_id", "station", "slot", "serial", "judged_at", "parameter", "value", "unit", "low",
               "high", "verdict")


def csv_text(report: SpcReport) -> str:
    """The report's points as CSV (one row per run), for a spreadsheet or the MES."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for p in report.points:
        w.writerow([p.run_id, p.batch_id, p.station, p.slot, p.serial, p.at or "", report.parameter, repr(p.value),
                    report.unit, "" if p.low is None else repr(p.low), "" if p.high is None else repr(p.high),
                    p.verdict or ""])
    return buf.getvalue()


__all__ = ["Point", "IChart", "Capability", "Histogram", "SlotTrend", "SpcReport", "YieldRow", "parameters", "series",
           "individuals", "capability", "histogram", "slot_trend", "spc_report", "yields", "csv_text"]
