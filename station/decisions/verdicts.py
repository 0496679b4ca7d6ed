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
satisfies, with the same guard band as the verdict (the spec's u_sys of that measurement included);
a passing DUT that meets no grade is `fail` with grade "none" and the spec's no-grade tray (its own
outcome, never the last grade by default); marginal -> "hold", fail -> "reject", error -> "retest".

The moment (design 8): `final_verdict(RunRecord, spec)` is THE verdict of a run, computed once from
everything the run stored when it ends (done, faulted, interrupted, aborted): the profile's own
requirements (`profile_requirements`: what its analysis and its program-and-verify must measure)
are required whatever the product's limits say, so a site config cannot make a verified profile
pass without its readback CRC, compensation and verified drift figures.

Measurements are a plain list, so any source can add one: the thermal analysis
(`thermal_measurements`), the SFEM (`sfem_measurements`), the link counters (`link_measurements`),
and later a verified drift error from program-and-verify (`Measurement("verified_drift_error_fs_pct",
...)`): a limit judges what is present, and a missing one only matters when its limit is required.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable

from station.decisions.limits import Limit, ProductSpec
from station.decisions.sfem_checks import RESIDUAL_RATIO, RESIDUAL_RATIO_UNIT, sfem_figures, sfem_fit_mark
from contracts.types import AXES

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
    """A real number that is finite (numpy scalars included; a bool is no measurement)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(float(v))


# ----------------------------------------------------------------------------------- judging
def judge(m: Measurement, limit: Limit, guard_sigma: float, u_sys: float | None = None) -> Check:
    """One measurement against one limit (see the module doc for the rules). `u_sys` overrides the
    limit's own systematic term (a grade's limit is judged with the spec's u_sys of the measurement)."""
    what = _what(limit, m.axis)
    unit = limit.unit or m.unit
    u_sys = limit.u_sys if u_sys is None else u_sys
    sigma = math.hypot(float(m.sigma) if _finite(m.sigma) else 0.0, u_sys) if (_finite(m.sigma) or u_sys) else None
    base = dict(measurement=m.name, axis=m.axis, value=m.value, sigma=sigma, unit=unit, low=limit.low, high=limit.high)
    if not _finite(m.value):
        return Check(**base, outcome="error", reason=f"{what} not measured")
    v = float(m.value)
    half = guard_sigma * sigma if sigma is not None else 0.0
    lo_v, hi_v = v - half, v + half
    pm = f" +-{fmt(sigma)} {unit} (1 sigma, k={fmt(guard_sigma)} band)" if half > 0 else f" {unit}"
    z = abs(v) / sigma if limit.evidence_sigma > 0 and sigma else None
    if z is not None and z >= limit.evidence_sigma:  # a model check the data reject (docs/verdicts.md "Curvature")
        what = f"{what} (linear model rejected, {z:.1f} sigma)"
    # wholly outside a limit: fail (the limit named is the one crossed; the interval is all outside,
    # so the words carry no uncertainty)
    if limit.low is not None and hi_v < limit.low:
        return Check(**base, outcome="fail", reason=f"{what} {fmt(v)} {unit}, limit {fmt(limit.low)}")
    if limit.high is not None and lo_v > limit.high:
        return Check(**base, outcome="fail", reason=f"{what} {fmt(v)} {unit}, limit {fmt(limit.high)}")
    crosses = (limit.low is not None and lo_v < limit.low) or (limit.high is not None and hi_v > limit.high)
    if crosses and z is not None and z < limit.evidence_sigma:  # no evidence, no hold
        return Check(**base, outcome="pass",
                     reason=f"{what} {fmt(v)}{pm}: not significant ({z:.1f} sigma < {fmt(limit.evidence_sigma)})")
    # the interval crosses a limit: the data cannot tell
    if limit.low is not None and lo_v < limit.low:
        return Check(**base, outcome="marginal", reason=f"{what} {fmt(v)}{pm} crosses limit {fmt(limit.low)}")
    if limit.high is not None and hi_v > limit.high:
        return Check(**base, outcome="marginal", reason=f"{what} {fmt(v)}{pm} crosses limit {fmt(limit.high)}")
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


# Measurements that come per axis (x, y, z); every other one is one number per run.
PER_AXIS = frozenset({
    "tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_fs_pct", "drift_error_mg", "bow_mg", "ramp_residual_rms_mg",
    "fit_agreement_tdb_mg_per_c", "fit_agreement_tdsf_ppm_per_c", "noise_ug_per_sqrt_hz", "sfem_bias_mg",
    "sfem_scale_error_pct", "verified_drift_error_fs_pct",
})


def _presence(name: str, unit: str = "", label: str = "") -> Limit:
    """A requirement with no limit of the product's: present and finite is all it asks."""
    return Limit.model_construct(measurement=name, low=None, high=None, unit=unit, label=label or name, required=True,
                                 analysis="any")


def _missing_checks(limit: Limit, found: list[Measurement]) -> list[Check]:
    """Error checks for a required limit's missing measurements (per axis: every axis it names)."""
    if found and not any(m.axis is not None for m in found):
        return []
    per_axis = limit.measurement in PER_AXIS or any(m.axis is not None for m in found) or limit.axes is not None
    have = {m.axis for m in found}
    axes = (limit.axes or list(AXES)) if per_axis else [None]
    return [Check(limit.measurement, ax, None, None, limit.unit, limit.low, limit.high, "error",
                  f"{_what(limit, ax)} not measured") for ax in axes if ax not in have]


def _limits_in_force(spec: ProductSpec, analysis: str, required: Iterable[Limit | str]) -> list[Limit]:
    """The product's limits for this analysis, with the profile's requirements made required: a
    required name the product limits is judged by the product's limit(s); one it does not limit
    must still be present; a required Limit (a contract check such as the readback CRC) is added."""
    limits = [lim for lim in spec.limits if _applies(lim, analysis)]
    for req in required:
        if isinstance(req, Limit):
            limits.append(req)
            continue
        own = [i for i, lim in enumerate(limits) if lim.measurement == req]
        for i in own:
            limits[i] = limits[i].model_copy(update={"required": True})
        if not own:
            limits.append(_presence(req))
    return limits


def decide(
    measurements: Iterable[Measurement],
    spec: ProductSpec | None,
    *,
    analysis: str = "thermal",
    state: str = "done",
    fault_reason: str = "",
    required: Iterable[Limit | str] = (),
) -> Verdict:
    """The verdict of one DUT run. `state` is the run's end state: anything but 'done' is error.
    `required`: what the profile itself requires (profile_requirements), on top of the product."""
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
    for limit in _limits_in_force(spec, analysis, required):
        found = _matching(ms, limit)
        if limit.required:
            checks += _missing_checks(limit, found)
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
    grade, unmet = _grade(ms, spec)
    if grade is None:
        return Verdict("fail", NO_GRADE, spec.no_grade_tray, [f"meets no grade: {'; '.join(unmet)}"], checks, **ident)
    tray = next((g.tray for g in spec.grades if g.name == grade), "") or f"grade {grade}"
    return Verdict("pass", grade, tray, [], checks, **ident)


NO_GRADE = "none"


def _spec_u_sys(spec: ProductSpec, measurement: str) -> float:
    """The systematic term the spec's own limits give a measurement (a grade judges with it too)."""
    return max((lim.u_sys for lim in spec.limits if lim.measurement == measurement), default=0.0)


def _grade_unmet(ms: list[Measurement], spec: ProductSpec, grade: Any) -> str | None:
    """Why `grade` is not met (None = met): each of its limits on EVERY axis it applies to, with the
    verdict's guard band; a missing measurement is not met."""
    for limit in grade.limits:
        found = _matching(ms, limit)
        if not found or _missing_checks(limit.model_copy(update={"required": True}), found):
            return f"{grade.name}: {_what(limit, None)} not measured"
        u_sys = max(limit.u_sys, _spec_u_sys(spec, limit.measurement))
        for m in found:
            c = judge(m, limit, spec.guard_sigma, u_sys=u_sys)
            if c.outcome != "pass":
                return f"{grade.name}: {c.reason or _what(limit, m.axis)}"
    return None


def _grade(ms: list[Measurement], spec: ProductSpec) -> tuple[str | None, list[str]]:
    """(first grade met, why the earlier ones were not); (None, reasons) when none is met."""
    if not spec.grades:
        return "pass", []
    unmet: list[str] = []
    for g in spec.grades:
        why = _grade_unmet(ms, spec, g)
        if why is None:
            return g.name, unmet
        unmet.append(why)
    return None, unmet


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
    """The SFEM figures the verdict judges (station/decisions/sfem_checks.py): bias and scale of
    the step nearest t_ref_c with their 1-sigma, its held-out RMSE, the model check's residual ratio."""
    return [_m(*f) for f in sfem_figures(result)]


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


def program_measurements(program: dict | None) -> list[Measurement]:
    """Program-and-verify, part 1, as measurements: the readback CRC equal to the written one (1/0)
    and on-board compensation confirmed on (1/0). No record (never programmed, e.g. the write
    faulted the slot or a resume skipped the program step) -> nothing: the requirement reports it."""
    if not program or not program.get("programmed"):
        return []
    crc, rb = program.get("crc"), program.get("readback_crc")
    match = bool(crc) and crc == rb and program.get("readback_identical") is not False
    return [_m("program_crc_match", 1.0 if match else 0.0, "", source=f"written {crc}, read back {rb}"),
            _m("compensation_on", 1.0 if program.get("comp") else 0.0, "", source="CALR after COMP 1")]


def verification_measurements(verification: dict | None) -> list[Measurement]:
    """Program-and-verify, part 2: the verified drift error E_FS of the compensated output per axis
    (with its 1-sigma) and how many axes fail the verification's rules (ratio, curvature, rise)."""
    if not verification:
        return []
    e_fs = verification.get("e_after_fs_pct") or {}
    e_sig = verification.get("e_after_fs_sigma_pct") or {}
    out = [_m("verified_drift_error_fs_pct", e_fs.get(ax), "%FS", ax, e_sig.get(ax), "program-and-verify")
           for ax in AXES if _finite(e_fs.get(ax))]
    axes = verification.get("axes") or {}
    if axes:
        failed = sum(1 for a in AXES if not (axes.get(a) or {}).get("passed", False))
        out.append(_m("verify_failed_axes", float(failed), "axes", source="program-and-verify"))
    return out


# What a profile itself requires, whatever the product's limits (design 8). Contract checks of
# program-and-verify are fixed limits: a site cannot configure them away.
ANALYSIS_REQUIREMENTS: dict[str, tuple[str, ...]] = {
    "thermal": ("tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_fs_pct", "bow_mg", "lost_samples_pct"),
    "sfem": ("sfem_bias_mg", "sfem_scale_error_pct", "lost_samples_pct"),
    "none": (),
}
PROGRAM_VERIFY_REQUIREMENTS: tuple[Limit | str, ...] = (
    Limit(measurement="program_crc_match", low=1.0, high=1.0, label="readback CRC equal to the written one",
          required=True, analysis="any"),
    Limit(measurement="compensation_on", low=1.0, high=1.0, label="on-board compensation on", required=True,
          analysis="any"),
    "verified_drift_error_fs_pct",
    Limit(measurement="verify_failed_axes", high=0.0, unit="axes", label="axes failing the verification",
          required=True, analysis="any"),
)


def profile_requirements(analysis: str, program_verify: bool) -> tuple[Limit | str, ...]:
    """Measurements (names, or fixed contract limits) a run of this profile must have to pass."""
    return tuple(ANALYSIS_REQUIREMENTS.get(analysis, ())) + (PROGRAM_VERIFY_REQUIREMENTS if program_verify else ())


@dataclass(frozen=True)
class RunRecord:
    """Everything a run stored that its verdict stands on, as plain data (from a live DutRun, a
    resumed one or the database alike)."""

    analysis: str  # the profile's analysis: thermal, sfem, none
    program_verify: bool  # the profile ends with program and verify
    end_state: str  # done, faulted, interrupted, aborted, ... (anything but done is error)
    end_reason: str = ""
    result: dict | None = None  # thermal or SFEM result
    link_stats: dict | None = None
    n_samples: int = 0
    program: dict | None = None
    verification: dict | None = None


def run_measurements(run: RunRecord) -> list[Measurement]:
    ms: list[Measurement] = []
    if run.analysis == "thermal":
        ms += thermal_measurements(run.result)
    elif run.analysis == "sfem":
        ms += sfem_measurements(run.result)
    ms += link_measurements(run.link_stats, run.n_samples)
    if run.program_verify:
        ms += program_measurements(run.program) + verification_measurements(run.verification)
    return ms


def final_verdict(run: RunRecord, spec: ProductSpec | None) -> Verdict:
    """THE verdict of a run (design 8): once, from its final state. Pass only when the run ended
    done and every measurement its profile and product require is present and inside its limits
    after the guard band."""
    v = decide(run_measurements(run), spec, analysis=run.analysis, state=run.end_state,
               fault_reason=run.end_reason, required=profile_requirements(run.analysis, run.program_verify))
    if v.verdict == "error" and run.end_state == "done" and run.program_verify:
        v.reasons[:0] = _program_verify_causes(run)  # the cause first, then what it left unmeasured
    if run.analysis == "sfem" and run.end_state == "done" and spec is not None:
        _mark_sfem_fit(v, run.result)
    return v


def _mark_sfem_fit(v: Verdict, result: dict | None) -> None:
    """The SFEM model check marks the verdict, it never decides it (sfem_checks.py says why): a
    check with its words, and the words among the reasons when the model misses an effect."""
    mark = sfem_fit_mark(result)
    if mark is None or any(c.measurement == RESIDUAL_RATIO for c in v.checks):
        return  # no record, or the product's own limit judged the ratio
    v.checks.append(Check(RESIDUAL_RATIO, None, mark[0], None, RESIDUAL_RATIO_UNIT, None, None, "pass", mark[1]))
    if "misses an effect" in mark[1]:
        v.reasons.append(mark[1])


def _program_verify_causes(run: RunRecord) -> list[str]:
    """Why a verified run lacks its program-and-verify figures, in the operator's words."""
    out = []
    prog = run.program or {}
    if not prog.get("programmed"):
        out.append("not programmed: " + (prog.get("error") or "no programming record in this run "
                                         "(resumed after its program step?)"))
    ver = run.verification or {}
    if not (ver.get("e_after_fs_pct") or {}) and ver.get("flags"):
        out.append("not verified: " + str(ver["flags"][0]))
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


__all__ = ["Measurement", "Check", "Verdict", "RunRecord", "decide", "final_verdict", "judge", "thermal_measurements",
           "sfem_measurements", "link_measurements", "program_measurements", "verification_measurements",
           "run_measurements", "profile_requirements", "summarize", "fmt", "VERDICTS", "NO_GRADE", "PER_AXIS"]
