"""The station decides: measurements + a product's limits -> verdict, grade and tray per DUT.

Pure (no I/O, no clock): dicts and dataclasses in, a Verdict out, so the same code judges a live
batch, a replay and a stored run, and the tests check it against hand-computed cases.

Verdicts:
    pass      every limited measurement's uncertainty interval lies inside its limits, outside any
              marginal band;
    marginal  some interval (value +- guard_sigma * sigma) crosses a limit, or a value lies within
              the limit's marginal band; the part may be good or bad, the data cannot tell;
    fail      some interval lies wholly outside a limit (every such measurement is named);
    error     the DUT faulted, the batch ended before it completed, its analysis failed, or a
              required measurement is missing: never `pass`.
Grades: a passing DUT gets the first grade (in config order) whose extra limits every interval
satisfies; marginal -> "hold", fail -> "reject", error -> "retest" (each with its tray).

Measurements are a plain list, so any source can add one: the thermal analysis
(`thermal_measurements`), the SFEM (`sfem_measurements`), the link counters (`link_measurements`),
and later a verified drift error from program-and-verify (`Measurement("verified_drift_error_fs_pct",
...)`): a limit judges what is present, and a missing one only matters when its limit is required.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable

from station.spec_limits import Limit, ProductSpec
from station.types import AXES

VERDICTS = ("pass", "marginal", "fail", "error")
_RANK = {"pass": 0, "marginal": 1, "fail": 2, "error": 3}


@dataclass(frozen=True)
class Measurement:
    """One measured number: value and 1-sigma uncertainty (None = not known) in `unit`."""

    name: str
    value: float | None
    unit: str = ""
    axis: str | None = None
    sigma: float | None = None
    source: str = ""


@dataclass(frozen=True)
class Check:
    """One measurement against one limit."""

    measurement: str
    axis: str | None
    value: float | None
    sigma: float | None  # combined standard uncertainty: measured (+) the limit's u_sys
    unit: str
    low: float | None
    high: float | None
    outcome: str  # pass, marginal, fail, error
    reason: str = ""


@dataclass
class Verdict:
    verdict: str
    grade: str | None
    tray: str
    reasons: list[str] = field(default_factory=list)
    checks: list[Check] = field(default_factory=list)
    product: str | None = None
    limits_name: str | None = None
    limits_version: str | None = None

    @property
    def reason(self) -> str:
        """One line for the operator: the worst reasons first (at most 3, then '+N more'; all of
        them are in `reasons`), or 'all limits met'."""
        if self.reasons:
            more = len(self.reasons) - 3
            return "; ".join(self.reasons[:3]) + (f"; +{more} more" if more > 0 else "")
        return "all limits met" if self.verdict == "pass" else ""

    def to_json(self) -> dict:
        return {
            "verdict": self.verdict,
            "grade": self.grade,
            "tray": self.tray,
            "reason": self.reason,
            "reasons": list(self.reasons),
            "failures": [asdict(c) for c in self.checks if c.outcome in ("fail", "marginal", "error")],
            "checks": [asdict(c) for c in self.checks],
            "product": self.product,
            "limits_name": self.limits_name,
            "limits_version": self.limits_version,
        }


# ----------------------------------------------------------------------------------- formatting
def fmt(v: float | None) -> str:
    """A number as an operator reads it: 3 significant digits, no exponent for usual sizes."""
    if v is None or not math.isfinite(v):
        return "n/a"
    if abs(v) >= 100:
        return f"{v:.0f}"
    return f"{v:.3g}"


def _what(limit: Limit, axis: str | None) -> str:
    label = limit.label or limit.measurement
    return f"{axis} {label}" if axis else label


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(float(v))


# ----------------------------------------------------------------------------------- judging
def judge(m: Measurement, limit: Limit, guard_sigma: float) -> Check:
    """One measurement against one limit (see the module doc for the rules)."""
    what = _what(limit, m.axis)
    unit = limit.unit or m.unit
    sigma = math.hypot(float(m.sigma) if _finite(m.sigma) else 0.0, limit.u_sys) if (_finite(m.sigma) or limit.u_sys) else None
    base = dict(measurement=m.name, axis=m.axis, value=m.value, sigma=sigma, unit=unit, low=limit.low, high=limit.high)
    if not _finite(m.value):
        return Check(**base, outcome="error", reason=f"{what} not measured")
    v = float(m.value)
    half = guard_sigma * sigma if sigma is not None else 0.0
    lo_v, hi_v = v - half, v + half
    pm = f" +-{fmt(half)}" if half > 0 else ""
    # wholly outside a limit: fail (the limit named is the one crossed)
    if limit.low is not None and hi_v < limit.low:
        return Check(**base, outcome="fail", reason=f"{what} {fmt(v)} {unit}, limit {fmt(limit.low)}")
    if limit.high is not None and lo_v > limit.high:
        return Check(**base, outcome="fail", reason=f"{what} {fmt(v)} {unit}, limit {fmt(limit.high)}")
    # the interval crosses a limit: the data cannot tell
    if limit.low is not None and lo_v < limit.low:
        return Check(**base, outcome="marginal",
                     reason=f"{what} {fmt(v)}{pm} {unit} crosses limit {fmt(limit.low)}")
    if limit.high is not None and hi_v > limit.high:
        return Check(**base, outcome="marginal",
                     reason=f"{what} {fmt(v)}{pm} {unit} crosses limit {fmt(limit.high)}")
    # inside, but within the marginal band
    if limit.marginal > 0:
        if limit.low is not None and lo_v < limit.low + limit.marginal:
            return Check(**base, outcome="marginal",
                         reason=f"{what} {fmt(v)} {unit}, within {fmt(limit.marginal)} of limit {fmt(limit.low)}")
        if limit.high is not None and hi_v > limit.high - limit.marginal:
            return Check(**base, outcome="marginal",
                         reason=f"{what} {fmt(v)} {unit}, within {fmt(limit.marginal)} of limit {fmt(limit.high)}")
    return Check(**base, outcome="pass")


def _matching(measurements: list[Measurement], limit: Limit) -> list[Measurement]:
    out = [m for m in measurements if m.name == limit.measurement]
    if limit.axes is not None:
        out = [m for m in out if m.axis in limit.axes]
    return out


def _applies(limit: Limit, analysis: str) -> bool:
    return limit.analysis == "any" or limit.analysis == analysis


def decide(
    measurements: Iterable[Measurement],
    spec: ProductSpec | None,
    *,
    analysis: str = "thermal",
    state: str = "done",
    fault_reason: str = "",
) -> Verdict:
    """The verdict of one DUT run. `state` is the run's end state: anything but 'done' is error."""
    ms = list(measurements)
    ident = dict(product=spec.sensor if spec else None, limits_name=spec.name if spec else None,
                 limits_version=spec.version if spec else None)
    error_tray = spec.error_tray if spec else "retest"
    if state != "done":
        why = fault_reason or f"run {state}: incomplete"
        return Verdict("error", "retest", error_tray, [why], [], **ident)
    if spec is None:
        return Verdict("error", "retest", error_tray, ["no spec limits for this sensor / part number"], [], **ident)
    checks: list[Check] = []
    for limit in spec.limits:
        if not _applies(limit, analysis):
            continue
        found = _matching(ms, limit)
        if limit.required and (not found or any(m.axis is not None for m in found)):
            have = {m.axis for m in found}
            for ax in limit.axes or list(AXES):  # a per-axis measurement is needed on every axis
                if ax not in have:
                    checks.append(Check(limit.measurement, ax, None, None, limit.unit, limit.low, limit.high, "error",
                                        f"{_what(limit, ax)} not measured"))
        for m in found:
            c = judge(m, limit, spec.guard_sigma)
            if c.outcome == "error" and not limit.required:
                continue  # an optional measurement that came out empty is not judged
            checks.append(c)
    worst = max((c.outcome for c in checks), key=_RANK.__getitem__, default="pass")
    order = sorted((c for c in checks if c.outcome != "pass"), key=lambda c: -_RANK[c.outcome])
    reasons = [c.reason for c in order]
    if worst == "error":
        return Verdict("error", "retest", spec.error_tray, reasons, checks, **ident)
    if worst == "fail":
        return Verdict("fail", "reject", spec.reject_tray, reasons, checks, **ident)
    if worst == "marginal":
        return Verdict("marginal", "hold", spec.marginal_tray, reasons, checks, **ident)
    grade = _grade(ms, spec)
    tray = next((g.tray for g in spec.grades if g.name == grade), "") or f"grade {grade}"
    return Verdict("pass", grade, tray, [], checks, **ident)


def _grade(ms: list[Measurement], spec: ProductSpec) -> str:
    """First grade whose every extra limit each matching interval satisfies (missing = not met)."""
    for g in spec.grades:
        ok = True
        for limit in g.limits:
            found = _matching(ms, limit)
            if not found or any(judge(m, limit, spec.guard_sigma).outcome != "pass" for m in found):
                ok = False
                break
        if ok:
            return g.name
    return spec.grades[-1].name if spec.grades else "pass"


# ----------------------------------------------------------------------------------- measurements
def _m(name: str, value: Any, unit: str, axis: str | None = None, sigma: Any = None, source: str = "") -> Measurement:
    v = float(value) if _finite(value) else None
    s = float(sigma) if _finite(sigma) else None
    return Measurement(name, v, unit, axis, s, source)


def thermal_measurements(result: dict | None) -> list[Measurement]:
    """From a thermal result (the `station calibrate --json` shape plus its "residual" report)."""
    if not result:
        return []
    out: list[Measurement] = []
    axes = result.get("axes") or {}
    streaming = (result.get("streaming") or {}).get("axes") or {}
    residual = (result.get("residual") or {}).get("axes") or {}
    for ax in AXES:
        a = axes.get(ax) or {}
        if a:
            out.append(_m("tdb_mg_per_c", a.get("tdb_mg_per_c"), "mg/C", ax, a.get("tdb_sigma_mg_per_c"), "offline"))
            out.append(_m("tdsf_ppm_per_c", a.get("tdsf_ppm_per_c"), "ppm/C", ax, a.get("tdsf_sigma_ppm_per_c"), "offline"))
        s = streaming.get(ax) or {}
        if a and s and _finite(a.get("tdb_mg_per_c")) and _finite(s.get("tdb_mg_per_c")):
            out.append(_m("fit_agreement_tdb_mg_per_c", abs(s["tdb_mg_per_c"] - a["tdb_mg_per_c"]), "mg/C", ax,
                          source="streaming vs offline"))
        if a and s and _finite(a.get("tdsf_ppm_per_c")) and _finite(s.get("tdsf_ppm_per_c")):
            out.append(_m("fit_agreement_tdsf_ppm_per_c", abs(s["tdsf_ppm_per_c"] - a["tdsf_ppm_per_c"]), "ppm/C", ax,
                          source="streaming vs offline"))
        r = residual.get(ax) or {}
        if r:
            out.append(_m("drift_error_fs_pct", r.get("drift_error_fs_pct"), "%FS", ax, r.get("drift_error_fs_sigma_pct"),
                          "eqs. 10-12"))
            out.append(_m("drift_error_mg", r.get("drift_error_mg"), "mg", ax, r.get("drift_error_sigma_mg"), "eq. 10"))
            out.append(_m("bow_mg", r.get("bow_mg"), "mg", ax, r.get("bow_sigma_mg"), "curvature"))
            out.append(_m("ramp_residual_rms_mg", r.get("ramp_residual_rms_mg"), "mg", ax, source="own ramp"))
            out.append(_m("noise_ug_per_sqrt_hz", r.get("noise_ug_per_sqrt_hz"), "ug/sqrt(Hz)", ax, source="stable samples"))
    return out


def sfem_measurements(result: dict | None) -> list[Measurement]:
    """Bias (mg) and |scale - 1| (%) per axis, with their 1-sigma, from an SFEM result: the fit of
    the first temperature step (the supervisor's {"temperatures": [{"fit": ...}]}) or one fit
    (`station sfem --json`: "bias" in g, "scale" diagonal of S, "*_sigma")."""
    if not result:
        return []
    temps = result.get("temperatures") or []
    fit = (temps[0] or {}).get("fit") if temps else result
    if not isinstance(fit, dict):
        return []
    out: list[Measurement] = []
    bias, bias_sig = fit.get("bias"), fit.get("bias_sigma")
    scale, scale_sig = fit.get("scale"), fit.get("scale_sigma")

    def at(v: Any, k: int) -> Any:
        return v[k] if isinstance(v, (list, tuple)) and len(v) == 3 else None

    for k, ax in enumerate(AXES):
        b, sb = at(bias, k), at(bias_sig, k)
        if _finite(b):
            out.append(_m("sfem_bias_mg", float(b) * 1e3, "mg", ax, float(sb) * 1e3 if _finite(sb) else None, "sfem"))
        sc, ss = at(scale, k), at(scale_sig, k)
        if _finite(sc):
            out.append(_m("sfem_scale_error_pct", abs(float(sc) - 1.0) * 100.0, "%", ax,
                          float(ss) * 100.0 if _finite(ss) else None, "sfem"))
    return out


def link_measurements(link_stats: dict | None, n_samples: int) -> list[Measurement]:
    """Lost samples (% of expected) and link errors (bad/malformed frames, board error replies)."""
    st = link_stats or {}
    lost = int(st.get("samples_lost", 0) or 0)
    total = int(n_samples) + lost
    out = [_m("link_errors", sum(int(st.get(k, 0) or 0) for k in ("frames_bad_checksum", "frames_malformed",
                                                                   "errors_reported")), "frames", source="link")]
    if total > 0:
        out.append(_m("lost_samples_pct", 100.0 * lost / total, "%", source="link"))
    return out


def summarize(verdicts: Iterable[dict | None]) -> dict:
    """Counts per verdict and per grade of a batch's DUTs (None = not judged yet)."""
    counts = {v: 0 for v in VERDICTS}
    grades: dict[str, int] = {}
    judged = 0
    for v in verdicts:
        if not v:
            continue
        judged += 1
        counts[v["verdict"]] = counts.get(v["verdict"], 0) + 1
        g = v.get("grade")
        if g:
            grades[g] = grades.get(g, 0) + 1
    return {"judged": judged, "verdicts": counts, "grades": grades}


__all__ = ["Measurement", "Check", "Verdict", "decide", "judge", "thermal_measurements", "sfem_measurements",
           "link_measurements", "summarize", "fmt", "VERDICTS"]
