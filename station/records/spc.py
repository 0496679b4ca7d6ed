"""Yield and statistical process control over judged DUT runs. Pure: plain dicts in
(the runs as db.repository.judged_runs gives them), typed dataclasses out; numpy only.

A parameter is one judged measurement, `measurement` or `measurement:axis` (e.g.
`tdb_mg_per_c:z`), taken from each run's verdict checks (station/decisions/verdicts.py).

**One chart per product and limits version.** Runs are grouped by (product, limits name, limits
version); product = part number + revision of the batch (contracts/trace.py; '' = unspecified
product, e.g. runs from before work orders were recorded). A chart, its control limits, its run
rules and its Cpk never mix groups: two products have two processes, and a Cpk against two sets
of limits is no number at all.

**Every point is judged by its own run's limits** (the check carries them): the out-of-spec count
and the point's "above USL / below LSL" come from that run's low/high, never from the newest run's.
Within one limits version the limits should be one set; if they differ (a set edited without a
version bump, which the limits audit also flags) Cpk is not computed and says why.

- Individuals chart (I-MR): centre = mean; sigma_within = MR-bar / d2 (d2 = 1.128 for moving
  ranges of two); limits mean ± 3 sigma_within (= ± 2.66 MR-bar); MR chart UCL = D4 MR-bar
  (D4 = 3.267). Run rules 1-8 and the MR flag name the points (station/records/spc_rules.py).
- Capability: Cpk = min(USL - mean, mean - LSL) / (3 sigma_within) (the short-term figure SPC uses),
  Ppk the same with the overall sample sigma. One-sided limits give the one side; none give None.
  Only from n >= CPK_MIN_N, with a confidence interval (see `cpk_interval`).
- Histogram with the spec limits; per-slot trend (mean per slot: a slot that reads high is a
  fixture or board-link problem, not a process shift).
- Yield per batch, day (UTC), product, limits set and station: pass / judged.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass, field, replace
from statistics import NormalDist
from typing import Any, Iterable

import numpy as np

from station.records import parameter_names as names
from station.records.csv_cells import safe_row
from station.records.spc_rules import RULE_NAMES, flags as rule_flags
from station.records.spc_yield import UNSPECIFIED, VERDICTS, YIELD_BY, YieldRow, utc_text as _utc, yields  # noqa: F401 (re-exported)

D2_MR2 = 1.128  # d2 for subgroups of 2 (moving range)
D4_MR2 = 3.267  # D4 for subgroups of 2
# Cpk from fewer parts is not reported. 25 because (a) AIAG's SPC manual and Montgomery ask for 20-25
# subgroups before control limits (and so sigma_within) are trusted, and (b) at n = 25 the 95 %
# interval of a Cpk near 1.33 is already about ±0.50 (`cpk_interval`): 1.33 cannot be told from 0.83
# or 1.83. At n = 12 it is ±0.73, a number that only looks like information.
CPK_MIN_N = 25
MR_DF_FACTOR = 0.62  # degrees of freedom of MR-bar/d2 per (n - 1), Cryer & Ryan 1990 (see cpk_interval)
CPK_TARGET = 1.33  # the usual customer minimum; a lower Cpk is highlighted
CI_LEVEL = 0.95


@dataclass(frozen=True)
class Flag:
    rule: str  # "1".."8" (Nelson) or "MR"
    name: str  # in words


@dataclass(frozen=True)
class Point:
    index: int  # 1-based position in the chart (the x axis)
    run_id: int
    batch_id: int
    station: str
    slot: str
    serial: str
    work_order: str
    at: str | None  # judged at, UTC "YYYY-MM-DDTHH:MM:SSZ"
    value: float
    low: float | None  # this run's own limits
    high: float | None
    verdict: str | None  # the run's verdict
    outcome: str | None  # this check's outcome as the station judged it (guard band included)
    spec: str  # "in spec", "above USL", "below LSL": the value against its own limits
    out_of_spec: bool  # spec != "in spec"
    flags: tuple[Flag, ...] = ()


@dataclass(frozen=True)
class Group:
    key: str  # opaque, as the API takes it back (`group=`)
    product: str  # '' = unspecified
    limits_name: str
    limits_version: str
    label: str
    runs: int
    last_at: str | None


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
    out_of_control: list[int] = field(default_factory=list)  # indices (0-based) beyond the limits (rule 1)
    flagged: list[int] = field(default_factory=list)  # indices with any rule or MR flag
    rule_counts: dict[str, int] = field(default_factory=dict)


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
    out_of_spec: int  # points outside their OWN run's limits
    min_n: int = CPK_MIN_N
    reason: str | None = None  # why cpk/ppk are None ("n=12 < 25")
    cpk_ci_low: float | None = None
    cpk_ci_high: float | None = None
    ci_level: float = CI_LEVEL
    target: float = CPK_TARGET
    below_target: bool | None = None  # cpk < target (None: no cpk)


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
    label: str  # "TDB x (mg/°C)"
    unit: str  # as the checks carry it ("mg/C")
    group: Group | None
    points: list[Point]
    chart: IChart
    capability: Capability
    histogram: Histogram
    slots: list[SlotTrend]

    def to_json(self) -> dict:
        return asdict(self)


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


# ---- groups: product x limits version ----------------------------------------------------------------
def group_of(run: dict) -> tuple[str, str, str]:
    return (str(run.get("product") or ""), str(run.get("limits_name") or ""), str(run.get("limits_version") or ""))


def _esc(s: str) -> str:
    return s.replace("%", "%25").replace("|", "%7C")


def group_key(g: tuple[str, str, str]) -> str:
    """Injective: a '|' inside a field is escaped, so two groups never share a key."""
    return "|".join(_esc(f) for f in g)


def group_label(g: tuple[str, str, str]) -> str:
    product, name, version = g
    return f"{product or UNSPECIFIED} · {name or 'no limits set'} v{version or '?'}"


def groups(runs: Iterable[dict]) -> list[Group]:
    """Every group of the runs, the one with the newest judged run first."""
    count: dict[tuple, int] = {}
    last: dict[tuple, str] = {}
    for r in runs:
        g = group_of(r)
        count[g] = count.get(g, 0) + 1
        at = _utc(r.get("judged_at")) or ""
        last[g] = max(last.get(g, ""), at)
    order = sorted(count, key=lambda g: (last[g], g), reverse=True)
    return [Group(group_key(g), g[0], g[1], g[2], group_label(g), count[g], last[g] or None) for g in order]


def in_group(runs: Iterable[dict], key: str) -> list[dict]:
    return [r for r in runs if group_key(group_of(r)) == key]


# ---- points -------------------------------------------------------------------------------------------
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


def _spec(value: float, low: float | None, high: float | None) -> str:
    if high is not None and value > high:
        return "above USL"
    if low is not None and value < low:
        return "below LSL"
    return "in spec"


def series(runs: Iterable[dict], parameter: str) -> tuple[list[Point], str]:
    """The parameter's values in the order of the runs (judging time), each with its own run's limits."""
    points: list[Point] = []
    unit = ""
    for r in runs:
        for c in r.get("checks") or []:
            if isinstance(c, dict) and parameter_of(c) == parameter and _finite(c.get("value")):
                unit = unit or str(c.get("unit") or "")
                v = float(c["value"])
                low = float(c["low"]) if _finite(c.get("low")) else None
                high = float(c["high"]) if _finite(c.get("high")) else None
                spec = _spec(v, low, high)
                points.append(Point(len(points) + 1, int(r["run_id"]), int(r.get("batch_id") or 0),
                                    str(r.get("station") or ""), str(r.get("slot") or ""), str(r.get("serial") or ""),
                                    str(r.get("work_order") or ""), _utc(r.get("judged_at")), v, low, high,
                                    r.get("verdict"), c.get("outcome"), spec, spec != "in spec"))
                break
    return points, unit


# ---- chart and capability ----------------------------------------------------------------------------
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


def cpk_interval(cpk: float, n: int, level: float = CI_LEVEL, df_factor: float = MR_DF_FACTOR) -> tuple[float, float]:
    """Two-sided confidence interval of Cpk: Bissell's normal approximation (Bissell 1990, Applied
    Statistics 39(2)) with the degrees of freedom of the sigma actually used,

        Cpk ± z(1 - a/2) * sqrt( 1/(9n) + Cpk² / (2 nu) ),   nu = df_factor * (n - 1).

    Bissell derives it for sigma from the sample standard deviation (nu = n - 1). Cpk here uses
    sigma_within = MR-bar / d2, which carries less information: about 0.62 (n - 1) degrees of freedom
    (Cryer & Ryan 1990, J. Quality Technology 22(3)). With nu = n - 1 the interval covered the true
    Cpk only 88-89 % of the time for n = 25..100; with 0.62 (n - 1), 94-95 % (tests/test_spc.py
    simulates it).

    Assumptions: the n values are independent, normally distributed, and from a process in control
    (one stable mean and sigma). Correlated or autocorrelated data (a drifting chamber, parts of one
    wafer in a row) make it OPTIMISTIC, far too narrow (AR(1) with phi 0.7, n = 50: it held the true
    Cpk in 6 % of the simulated cases): read it as a lower bound on the uncertainty then. The same
    formula holds for the one-sided index (Cpu or Cpl) when only one limit exists."""
    z = NormalDist().inv_cdf(0.5 + level / 2)
    se = math.sqrt(1.0 / (9 * n) + cpk * cpk / (2 * df_factor * (n - 1)))
    return cpk - z * se, cpk + z * se


def capability(values: list[float], low: float | None, high: float | None, sigma_within: float | None,
               out_of_spec: int | None = None, min_n: int = CPK_MIN_N, limits_differ: str | None = None) -> Capability:
    """Cpk/Ppk of `values` against ONE set of limits (low, high). `out_of_spec` is the count by each
    point's own limits (computed against low/high when not given). `limits_differ`: why there is no
    one set (then no Cpk)."""
    x = np.asarray(values, dtype=float)
    n = len(x)
    if out_of_spec is None:
        out_of_spec = sum(_spec(float(v), low, high) != "in spec" for v in x)
    if n == 0:
        return Capability(0, low, high, None, None, None, None, None, 0, min_n, "no values")
    mean = float(x.mean())
    overall = float(x.std(ddof=1)) if n > 1 else None
    cap = Capability(n, low, high, mean, sigma_within, overall, None, None, int(out_of_spec), min_n)
    if limits_differ:
        cap.reason = limits_differ
    elif n < min_n:
        cap.reason = f"n={n} < {min_n}"
    elif low is None and high is None:
        cap.reason = "no spec limits"
    else:
        cap.cpk = _one_sided(mean, sigma_within, low, high)
        cap.ppk = _one_sided(mean, overall, low, high)
        if cap.cpk is None:
            cap.reason = "sigma is 0 (all values equal)"
        else:
            cap.cpk_ci_low, cap.cpk_ci_high = cpk_interval(cap.cpk, n)
            cap.below_target = cap.cpk < CPK_TARGET
    return cap


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


def spc_report(runs: list[dict], parameter: str, bins: int = 12, group: Group | None = None,
               min_n: int = CPK_MIN_N) -> SpcReport:
    """The chart of one parameter over `runs`, which the caller has narrowed to ONE group
    (`in_group`); `group` is only carried into the answer."""
    points, unit = series(runs, parameter)
    values = [p.value for p in points]
    chart = individuals(values)
    codes = rule_flags(values, chart.mean, chart.sigma_within, chart.mr_ucl)
    points = [replace(p, flags=tuple(Flag(c, RULE_NAMES[c]) for c in cs)) for p, cs in zip(points, codes)]
    chart.flagged = [i for i, cs in enumerate(codes) if cs]
    chart.rule_counts = {c: n for c in RULE_NAMES if (n := sum(c in cs for cs in codes))}
    sets = sorted({(p.low, p.high) for p in points}, key=str)
    low, high = sets[0] if len(sets) == 1 else (None, None)
    differ = None if len(sets) <= 1 else (f"{len(sets)} different sets of limits within this limits version (edited "
                                           "without a version bump?): Cpk needs one set")
    cap = capability(values, low, high, chart.sigma_within, sum(p.out_of_spec for p in points), min_n, differ)
    return SpcReport(parameter, names.label(parameter, unit) if parameter else "", unit, group, points, chart, cap,
                     histogram(values, low, high, bins), slot_trend(points))


@dataclass
class SpcView:
    """What the Records view shows: the groups under the filters, the one shown, its parameters."""

    groups: list[Group]
    parameters: list[str]
    labels: dict[str, str]  # parameter -> words with unit
    report: SpcReport


def spc_view(runs: list[dict], group: str | None = None, parameter: str | None = None,
             min_n: int = CPK_MIN_N) -> SpcView:
    """The chart of `parameter` in `group` (default: the group with the newest run, its first
    parameter). LookupError with the choices for an unknown group or parameter."""
    gs = groups(runs)
    if group is None:
        chosen = gs[0] if gs else None
    else:
        chosen = next((g for g in gs if g.key == group), None)
        if chosen is None:
            raise LookupError(f"group {group!r} has no judged runs under these filters; groups: "
                              + ("; ".join(f"{g.key!r} ({g.label})" for g in gs) or "none"))
    mine = in_group(runs, chosen.key) if chosen else []
    params = parameters(mine)
    if parameter is None:
        parameter = params[0] if params else ""
    elif parameter not in params:
        raise LookupError(f"parameter {parameter!r} not found in the judged runs of "
                          f"{chosen.label if chosen else 'no group'}; known: {', '.join(params) or 'none'}")
    units = {parameter_of(c): str(c.get("unit") or "") for r in mine for c in r.get("checks") or [] if isinstance(c, dict)}
    return SpcView(gs, params, {p: names.label(p, units.get(p, "")) for p in params},
                   spc_report(mine, parameter, group=chosen, min_n=min_n))


# ---- CSV: the points table of the Records view, column for column -------------------------------------
def csv_columns(report: SpcReport) -> list[str]:
    u = names.unit_words(names.split(report.parameter)[0], report.unit)
    return ["#", "run", "batch", "station", "slot", "serial", "judged (UTC)", f"value ({u})" if u else "value",
            "LSL", "USL", "own limits", "check", "flags"]


def flags_text(p: Point) -> str:
    return "; ".join(f"{f.rule}: {f.name}" for f in p.flags)


def csv_text(report: SpcReport) -> str:
    """The report's points as CSV, one row per run, in the columns the Records view's points table
    shows (numbers in full precision; an empty cell is no limit; text that a spreadsheet would take
    for a formula is quoted: station/records/csv_cells.py)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(csv_columns(report))
    for p in report.points:
        w.writerow(safe_row([p.index, p.run_id, p.batch_id, p.station, p.slot, p.serial, p.at or "", repr(p.value),
                             "" if p.low is None else repr(p.low), "" if p.high is None else repr(p.high), p.spec,
                             p.outcome or "", flags_text(p)]))  # a serial "=1+2" is text, not a formula
    return buf.getvalue()


__all__ = ["Flag", "Point", "Group", "IChart", "Capability", "Histogram", "SlotTrend", "SpcReport", "SpcView",
           "YieldRow", "yields", "YIELD_BY", "CPK_MIN_N", "CPK_TARGET", "CI_LEVEL", "groups", "group_key",
           "group_of", "in_group", "parameters", "series", "individuals", "capability", "cpk_interval", "histogram",
           "slot_trend", "spc_report", "spc_view", "csv_text", "csv_columns", "flags_text"]
