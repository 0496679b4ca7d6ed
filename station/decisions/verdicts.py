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

Where the parts are (this module decides; each part is its own module):
    measurements.py  every measurement declared once: name, unit, axes, 1-sigma, limit meaning, words
    readings.py      a run's stored results -> Measurements (`run_measurements`); what a profile requires
    judging.py       one measurement against one limit, in the operator's words (`judge`)
    checks.py        the verdict's checks, one registered object each (the product's limits, the SFEM
                     mark; a new check is one class and one `register(...)`)
Measurements are a plain list, so any source can add one: a limit judges what is present, and a
missing one only matters when its limit is required.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import asdict, dataclass, field, fields

from station.decisions.checks import RunView, run_checks
from station.decisions.judging import RANK, VERDICTS, Check, fmt, judge, matching, missing_checks, spec_u_sys, what
from station.decisions.limits import Grade, Limit, ProductSpec
from station.decisions.measurements import Measurement, declared, is_per_axis
from station.decisions.readings import (Record, RunRecord, link_measurements, profile_requirements,
                                        program_measurements, run_measurements, sfem_measurements,
                                        thermal_measurements, verification_measurements)

NO_GRADE = "none"
# The fields of a check and of a verdict's record (Verdict.to_json), and the decision a batch status,
# the MES summary and the run's columns carry of it (to_json's one-line fields + the attempt): the
# readers (web/schemas_common.py CheckOut, DecisionOut, DecisionFields, ...) are tested against these.
CHECK_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(Check))
VERDICT_FIELDS: tuple[str, ...] = ("verdict", "grade", "tray", "reason", "reasons", "failures", "checks", "product",
                                   "limits_name", "limits_version")
DECISION_FIELDS: tuple[str, ...] = ("verdict", "grade", "tray", "reason", "attempt", "limits_name", "limits_version")


class _PerAxis(AbstractSet[str]):
    """The names of the declared per-axis measurements (measurements.py), read when asked."""

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and is_per_axis(name)

    def __iter__(self) -> Iterator[str]:
        return iter([d.name for d in declared() if d.per_axis])

    def __len__(self) -> int:
        return sum(1 for d in declared() if d.per_axis)


# Measurements that come per axis (x, y, z); every other one is one number per run.
PER_AXIS: AbstractSet[str] = _PerAxis()


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

    def to_json(self) -> dict[str, object]:
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


# ----------------------------------------------------------------------------------- deciding
def decide(
    measurements: Iterable[Measurement],
    spec: ProductSpec | None,
    *,
    analysis: str = "thermal",
    state: str = "done",
    fault_reason: str = "",
    required: Iterable[Limit | str] = (),
    result: Record | None = None,
    verification: Record | None = None,
    board_selfcal: Record | None = None,
) -> Verdict:
    """The verdict of one DUT run. `state` is the run's end state: anything but 'done' is error.
    `required`: what the profile itself requires (profile_requirements), on top of the product.
    Every registered check (checks.py) judges the run; `result` is the analysis result as stored,
    for a check that reads it (the SFEM mark); `verification` and `board_selfcal` the program-and-verify
    record and the board calibrator's opinion, for the checks that read those."""
    ms = list(measurements)
    product, name, version = (spec.sensor, spec.name, spec.version) if spec else (None, None, None)

    def verdict(v: str, grade: str | None, tray: str, reasons: list[str], checks: list[Check]) -> Verdict:
        return Verdict(v, grade, tray, reasons, checks, product=product, limits_name=name, limits_version=version)

    error_tray = spec.error_tray if spec else "retest"
    if state != "done":
        return verdict("error", "retest", error_tray, [fault_reason or f"run {state}: incomplete"], [])
    if spec is None:
        return verdict("error", "retest", error_tray, ["no spec limits for this sensor / part number"], [])
    checks, marks = run_checks(RunView(tuple(ms), analysis, tuple(required), result, verification=verification,
                                       board_selfcal=board_selfcal), spec)
    worst = max((c.outcome for c in checks), key=RANK.__getitem__, default="pass")
    reasons = [c.reason for c in sorted((c for c in checks if c.outcome != "pass"), key=lambda c: -RANK[c.outcome])]
    if worst == "error":
        v = verdict("error", "retest", spec.error_tray, reasons, checks)
    elif worst == "fail":
        v = verdict("fail", "reject", spec.reject_tray, reasons, checks)
    elif worst == "marginal":
        v = verdict("marginal", "hold", spec.marginal_tray, reasons, checks)
    else:
        grade, unmet = _grade(ms, spec)
        if grade is None:
            v = verdict("fail", NO_GRADE, spec.no_grade_tray, [f"meets no grade: {'; '.join(unmet)}"], checks)
        else:
            tray = next((g.tray for g in spec.grades if g.name == grade), "") or f"grade {grade}"
            v = verdict("pass", grade, tray, [], checks)
    for mark in marks:  # words that never decide (checks.Mark)
        v.checks.append(mark.check)
        if mark.tell:
            v.reasons.append(mark.check.reason)
    return v


def _grade_unmet(ms: list[Measurement], spec: ProductSpec, grade: Grade) -> str | None:
    """Why `grade` is not met (None = met): each of its limits on EVERY axis it applies to, with the
    verdict's guard band; a missing measurement is not met."""
    for limit in grade.limits:
        found = matching(ms, limit)
        if not found or missing_checks(limit.model_copy(update={"required": True}), found):
            return f"{grade.name}: {what(limit, None)} not measured"
        u_sys = max(limit.u_sys, spec_u_sys(spec, limit.measurement))
        for m in found:
            c = judge(m, limit, spec.guard_sigma, u_sys=u_sys)
            if c.outcome != "pass":
                return f"{grade.name}: {c.reason or what(limit, m.axis)}"
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


def final_verdict(run: RunRecord, spec: ProductSpec | None) -> Verdict:
    """THE verdict of a run (design 8): once, from its final state. Pass only when the run ended
    done and every measurement its profile and product require is present and inside its limits
    after the guard band."""
    v = decide(run_measurements(run), spec, analysis=run.analysis, state=run.end_state, fault_reason=run.end_reason,
               required=profile_requirements(run.analysis, run.program_verify), result=run.result,
               verification=run.verification if run.program_verify else None, board_selfcal=run.board_selfcal)
    if v.verdict == "error" and run.end_state == "done" and run.program_verify:
        v.reasons[:0] = _program_verify_causes(run)  # the cause first, then what it left unmeasured
    return v


def _program_verify_causes(run: RunRecord) -> list[str]:
    """Why a verified run lacks its program-and-verify figures, in the operator's words."""
    out = []
    prog: Record = run.program or {}
    if not prog.get("programmed"):
        out.append("not programmed: " + str(prog.get("error") or "no programming record in this run "
                                            "(resumed after its program step?)"))
    ver: Record = run.verification or {}
    flags = ver.get("flags")
    if not (ver.get("e_after_fs_pct") or {}) and flags and isinstance(flags, Sequence):
        out.append("not verified: " + str(flags[0]))
    return out


def summarize(verdicts: Iterable[Mapping[str, object] | None]) -> dict[str, object]:
    """Counts per verdict and per grade of a batch's DUTs (None = not judged yet)."""
    counts = {v: 0 for v in VERDICTS}
    grades: dict[str, int] = {}
    judged = 0
    for v in verdicts:
        if not v:
            continue
        judged += 1
        verdict = str(v["verdict"])
        counts[verdict] = counts.get(verdict, 0) + 1
        g = v.get("grade")
        if g:
            grades[str(g)] = grades.get(str(g), 0) + 1
    return {"judged": judged, "verdicts": counts, "grades": grades}


__all__ = ["Measurement", "Check", "Verdict", "RunRecord", "decide", "final_verdict", "judge", "thermal_measurements",
           "sfem_measurements", "link_measurements", "program_measurements", "verification_measurements",
           "run_measurements", "profile_requirements", "summarize", "fmt", "VERDICTS", "NO_GRADE", "PER_AXIS",
           "CHECK_FIELDS", "VERDICT_FIELDS", "DECISION_FIELDS"]
