"""One measurement against one limit, in the operator's words (pure).

`judge` is the rule of docs/verdicts.md: a value's interval (value +- guard_sigma * sigma, sigma =
sqrt(sigma_measured^2 + u_sys^2)) wholly outside a limit fails, one that crosses it is marginal
(a model check only on evidence, `Limit.evidence_sigma`), one inside a marginal band is marginal,
anything else passes; the words name the measurement and the limit crossed ("z TDSF -612 ppm/C,
limit -500"). The rest is which measurements a limit judges (`matching`), which limits are in force
for a run (`limits_in_force`: the product's, with the profile's requirements made required) and
the error checks of a required measurement that is missing (`missing_checks`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from contracts.types import AXES
from station.decisions.limits import Limit, ProductSpec
from station.decisions.measurements import Measurement, finite, is_per_axis

Outcome = str  # pass, marginal, fail, error
VERDICTS: tuple[Outcome, ...] = ("pass", "marginal", "fail", "error")  # a check's outcomes and a run's verdicts
RANK: dict[Outcome, int] = {o: i for i, o in enumerate(VERDICTS)}  # the worse, the higher


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
    outcome: Outcome  # pass, marginal, fail, error
    reason: str = ""


def fmt(v: float | None) -> str:
    """A number as an operator reads it: 3 significant digits, no exponent for usual sizes."""
    if v is None or not math.isfinite(v):
        return "n/a"
    if abs(v) >= 100:
        return f"{v:.0f}"
    return f"{v:.3g}"


def what(limit: Limit, axis: str | None) -> str:
    """'z TDSF': the axis and the limit's words (its measurement's name when it has none)."""
    label = limit.label or limit.measurement
    return f"{axis} {label}" if axis else label


def judge(m: Measurement, limit: Limit, guard_sigma: float, u_sys: float | None = None) -> Check:
    """One measurement against one limit (see the module doc for the rules). `u_sys` overrides the
    limit's own systematic term (a grade's limit is judged with the spec's u_sys of the measurement)."""
    words = what(limit, m.axis)
    unit = limit.unit or m.unit
    u = limit.u_sys if u_sys is None else u_sys
    measured = float(m.sigma) if m.sigma is not None and finite(m.sigma) else None
    sigma = math.hypot(measured or 0.0, u) if (measured is not None or u) else None

    def check(outcome: Outcome, reason: str = "") -> Check:
        return Check(m.name, m.axis, m.value, sigma, unit, limit.low, limit.high, outcome, reason)

    if m.value is None or not finite(m.value):
        return check("error", f"{words} not measured")
    v = float(m.value)
    half = guard_sigma * sigma if sigma is not None else 0.0
    lo_v, hi_v = v - half, v + half
    pm = f" +-{fmt(sigma)} {unit} (1 sigma, k={fmt(guard_sigma)} band)" if half > 0 else f" {unit}"
    z = abs(v) / sigma if limit.evidence_sigma > 0 and sigma else None
    if z is not None and z >= limit.evidence_sigma:  # a model check the data reject (docs/verdicts.md "Curvature")
        words = f"{words} (linear model rejected, {z:.1f} sigma)"
    # wholly outside a limit: fail (the limit named is the one crossed; the interval is all outside,
    # so the words carry no uncertainty)
    if limit.low is not None and hi_v < limit.low:
        return check("fail", f"{words} {fmt(v)} {unit}, limit {fmt(limit.low)}")
    if limit.high is not None and lo_v > limit.high:
        return check("fail", f"{words} {fmt(v)} {unit}, limit {fmt(limit.high)}")
    crosses = (limit.low is not None and lo_v < limit.low) or (limit.high is not None and hi_v > limit.high)
    if crosses and z is not None and z < limit.evidence_sigma:  # no evidence, no hold
        return check("pass", f"{words} {fmt(v)}{pm}: not significant ({z:.1f} sigma < {fmt(limit.evidence_sigma)})")
    # the interval crosses a limit: the data cannot tell
    if limit.low is not None and lo_v < limit.low:
        return check("marginal", f"{words} {fmt(v)}{pm} crosses limit {fmt(limit.low)}")
    if limit.high is not None and hi_v > limit.high:
        return check("marginal", f"{words} {fmt(v)}{pm} crosses limit {fmt(limit.high)}")
    # inside, but within the marginal band
    if limit.marginal > 0:
        within = f"{words} {fmt(v)} {unit}, within {fmt(limit.marginal)} of limit"
        if limit.low is not None and lo_v < limit.low + limit.marginal:
            return check("marginal", f"{within} {fmt(limit.low)}")
        if limit.high is not None and hi_v > limit.high - limit.marginal:
            return check("marginal", f"{within} {fmt(limit.high)}")
    return check("pass")


def matching(measurements: Iterable[Measurement], limit: Limit) -> list[Measurement]:
    """The measurements a limit judges: its measurement's, on its axes."""
    out = [m for m in measurements if m.name == limit.measurement]
    if limit.axes is not None:
        out = [m for m in out if m.axis in limit.axes]
    return out


def presence(name: str, unit: str = "", label: str = "") -> Limit:
    """A requirement with no limit of the product's: present and finite is all it asks."""
    return Limit.model_construct(measurement=name, low=None, high=None, unit=unit, label=label or name, required=True,
                                 analysis="any")


def missing_checks(limit: Limit, found: Sequence[Measurement]) -> list[Check]:
    """Error checks for a required limit's missing measurements (per axis: every axis it names)."""
    if found and not any(m.axis is not None for m in found):
        return []
    per_axis = is_per_axis(limit.measurement) or any(m.axis is not None for m in found) or limit.axes is not None
    have = {m.axis for m in found}
    axes: list[str | None] = list(limit.axes or AXES) if per_axis else [None]
    return [Check(limit.measurement, ax, None, None, limit.unit, limit.low, limit.high, "error",
                  f"{what(limit, ax)} not measured") for ax in axes if ax not in have]


def limits_in_force(spec: ProductSpec, analysis: str, required: Iterable[Limit | str]) -> list[Limit]:
    """The product's limits for this analysis, with the profile's requirements made required: a
    required name the product limits is judged by the product's limit(s); one it does not limit
    must still be present; a required Limit (a contract check such as the readback CRC) is added."""
    limits = [lim for lim in spec.limits if lim.analysis == "any" or lim.analysis == analysis]
    for req in required:
        if isinstance(req, Limit):
            limits.append(req)
            continue
        own = [i for i, lim in enumerate(limits) if lim.measurement == req]
        for i in own:
            limits[i] = limits[i].model_copy(update={"required": True})
        if not own:
            limits.append(presence(req))
    return limits


def spec_u_sys(spec: ProductSpec, measurement: str) -> float:
    """The systematic term the spec's own limits give a measurement (a grade judges with it too)."""
    return max((lim.u_sys for lim in spec.limits if lim.measurement == measurement), default=0.0)


__all__ = ["Check", "Outcome", "VERDICTS", "RANK", "fmt", "what", "judge", "matching", "presence", "missing_checks",
           "limits_in_force", "spec_u_sys"]
