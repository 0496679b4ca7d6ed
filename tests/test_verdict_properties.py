"""Property-based test of the pure verdict core (station/decisions/verdicts.py, design 8): over random run
histories (measurements present, missing, NaN, numpy scalars; every end state; limits of every
shape: low only, high only, both, marginal bands, systematic terms, axis subsets, required or not;
grades with their own limits; with and without program-and-verify), a PASS implies

  - the run ended `done`;
  - every measurement the profile requires and every required limit's measurement is present and
    finite (on every axis it applies to);
  - every judged measurement's interval value +- k * sqrt(sigma^2 + u_sys^2) lies inside
    [low + marginal, high - marginal] of every limit in force;
  - the grade awarded has every one of its limits met the same way on every axis, with the spec's
    systematic term of that measurement.

The oracle below is written from the contract text, not from the code: it shares no helper with it.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from station.decisions.limits import Grade, Limit, ProductSpec
from station.decisions.verdicts import (
    PER_AXIS,
    RunRecord,
    Measurement,
    decide,
    final_verdict,
    profile_requirements,
    run_measurements,
)

AXES = ("x", "y", "z")
NAMES = ("tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_fs_pct", "bow_mg", "lost_samples_pct", "link_errors",
         "verified_drift_error_fs_pct", "verify_failed_axes", "program_crc_match", "compensation_on")
END_STATES = ("done", "faulted", "interrupted", "aborted", "connecting", "running", "identified")

# Small ranges on purpose: values, limits and intervals overlap often, so passes, marginals and
# grade boundaries are all common (a property over verdicts that are never `pass` proves nothing).
finite = st.floats(min_value=-10, max_value=10, allow_nan=False, allow_infinity=False)
value = st.one_of(finite, finite, finite.map(np.float32), finite.map(np.float64), st.just(float("nan")), st.just(None),
                  st.just(float("inf")))
sigma = st.one_of(st.none(), st.floats(min_value=0, max_value=2, allow_nan=False), st.just(float("nan")))


@st.composite
def limits(draw, measurement=None, for_grade=False):
    name = measurement or draw(st.sampled_from(NAMES))
    a, b = sorted(draw(st.tuples(st.floats(-20, 20), st.floats(-20, 20))))
    shape = draw(st.sampled_from(("low", "high", "both")))
    low = a if shape in ("low", "both") else None
    high = b if shape in ("high", "both") else None
    axes = draw(st.one_of(st.none(), st.lists(st.sampled_from(AXES), min_size=1, max_size=3, unique=True)))
    return Limit(measurement=name, low=low, high=high, axes=axes if name in PER_AXIS else None,
                 marginal=draw(st.floats(min_value=0, max_value=1)),
                 u_sys=0.0 if for_grade else draw(st.floats(min_value=0, max_value=2)),  # grades: as configs write them
                 required=False if for_grade else draw(st.booleans()), analysis=draw(st.sampled_from(("thermal", "any"))))


@st.composite
def specs(draw):
    grades = [Grade(name=f"G{i}", limits=draw(st.lists(limits(for_grade=True), max_size=3)))
              for i in range(draw(st.integers(1, 3)))]
    return ProductSpec(name="prop", version="1", sensor="LIS3DSH", guard_sigma=draw(st.sampled_from((0.0, 1.0, 2.0, 3.0))),
                       limits=draw(st.lists(limits(), min_size=1, max_size=6)), grades=grades)


@st.composite
def measurement_lists(draw):
    """Most names on every axis (so runs can pass), some on a few axes, some missing."""
    out = []
    for name in draw(st.lists(st.sampled_from(NAMES), min_size=4, max_size=12, unique=True)):
        every = draw(st.integers(0, 3)) > 0
        axes = (list(AXES) if every else draw(st.lists(st.sampled_from(AXES), min_size=1, max_size=3, unique=True))) \
            if name in PER_AXIS else [None]
        for ax in axes:
            out.append(Measurement(name, draw(value), "", ax, draw(sigma)))
    return out


# ----------------------------------------------------------------------------------- the oracle
def real(v) -> bool:
    return v is not None and not isinstance(v, bool) and math.isfinite(float(v))


def inside(m: Measurement, lim: Limit, k: float, u_sys: float) -> bool:
    """The contract's guarded acceptance: the whole interval inside the limits minus the marginal band."""
    if not real(m.value):
        return False
    s = math.hypot(float(m.sigma) if real(m.sigma) else 0.0, u_sys)
    lo, hi = float(m.value) - k * s, float(m.value) + k * s
    if lim.low is not None and lo < lim.low + lim.marginal:
        return False
    if lim.high is not None and hi > lim.high - lim.marginal:
        return False
    return True


def of(ms, name, axes=None):
    return [m for m in ms if m.name == name and (axes is None or m.axis in axes)]


def present_everywhere(ms, name, axes) -> bool:
    found = of(ms, name, axes)
    if name in PER_AXIS:
        return all(any(m.axis == ax and real(m.value) for m in found) for ax in (axes or AXES))
    return bool(found) and all(real(m.value) for m in found)


def assert_pass_is_earned(v, ms, spec, required_names, extra_limits, state):
    assert state == "done"
    for name in required_names:
        assert present_everywhere(ms, name, None), f"pass without required {name}"
    for lim in [*(lim for lim in spec.limits if lim.analysis in ("thermal", "any")), *extra_limits]:
        if lim.required:
            assert present_everywhere(ms, lim.measurement, lim.axes), f"pass without required {lim.measurement}"
        for m in of(ms, lim.measurement, lim.axes):
            if real(m.value) or lim.required or lim.measurement in required_names:
                assert inside(m, lim, spec.guard_sigma, lim.u_sys), f"pass with {m} outside {lim}"
    grade = next(g for g in spec.grades if g.name == v.grade)
    for lim in grade.limits:
        u = max([lim.u_sys] + [s.u_sys for s in spec.limits if s.measurement == lim.measurement])
        assert present_everywhere(ms, lim.measurement, lim.axes), f"grade {v.grade} without {lim.measurement}"
        for m in of(ms, lim.measurement, lim.axes):
            assert inside(m, lim, spec.guard_sigma, u), f"grade {v.grade} with {m} outside {lim}"


OUTCOMES: dict[str, int] = {}


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ms=measurement_lists(), spec=specs(), state=st.sampled_from(END_STATES + ("done",) * 6), pv=st.booleans(),
       with_profile=st.booleans())
def test_pass_implies_every_required_measurement_present_and_inside_its_guarded_limits(ms, spec, state, pv,
                                                                                      with_profile):
    required = profile_requirements("thermal", pv) if with_profile else ()
    v = decide(ms, spec, analysis="thermal", state=state, fault_reason="x", required=required)
    OUTCOMES[v.verdict] = OUTCOMES.get(v.verdict, 0) + 1
    if state != "done":
        assert v.verdict == "error"
    if v.verdict != "pass":
        assert v.tray and (v.reasons or v.verdict == "pass")
        return
    names = [r for r in required if isinstance(r, str)]
    extra = [r for r in required if isinstance(r, Limit)]
    assert_pass_is_earned(v, ms, spec, names, extra, state)


@settings(max_examples=200, deadline=None)
@given(state=st.sampled_from(END_STATES), crc_ok=st.booleans(), comp=st.booleans(), has_program=st.booleans(),
       e_fs=st.one_of(st.none(), st.floats(min_value=0, max_value=3)), e_sig=st.floats(min_value=0, max_value=0.5),
       axes_pass=st.booleans())
def test_a_verified_run_passes_only_with_its_crc_compensation_and_verified_figures(state, crc_ok, comp, has_program,
                                                                                  e_fs, e_sig, axes_pass):
    spec = ProductSpec(sensor="LIS3DSH", limits=[Limit(measurement="verified_drift_error_fs_pct", high=1.0)],
                       grades=[Grade(name="A")])
    result = {"axes": {a: {"tdb_mg_per_c": 0.1, "tdsf_ppm_per_c": -10.0} for a in AXES},
              "residual": {"axes": {a: {"drift_error_fs_pct": 0.2, "bow_mg": 0.1} for a in AXES}}}
    program = {"programmed": True, "crc": "0BADF00D", "readback_crc": "0BADF00D" if crc_ok else "DEADBEEF",
               "comp": comp} if has_program else None
    verification = None if e_fs is None else {
        "e_after_fs_pct": {a: e_fs for a in AXES}, "e_after_fs_sigma_pct": {a: e_sig for a in AXES},
        "axes": {a: {"passed": axes_pass} for a in AXES}}
    run = RunRecord("thermal", True, state, "", result, {"samples_lost": 0}, 1000, program, verification)
    v = final_verdict(run, spec)
    if v.verdict == "pass":
        assert state == "done" and has_program and crc_ok and comp and axes_pass
        assert e_fs is not None and e_fs + spec.guard_sigma * e_sig <= 1.0
    ms = run_measurements(run)
    assert (v.verdict == "pass") == (state == "done" and has_program and crc_ok and comp and axes_pass
                                     and e_fs is not None and e_fs + 2.0 * e_sig <= 1.0
                                     and present_everywhere(ms, "verified_drift_error_fs_pct", None))


def test_the_property_saw_every_outcome():
    """The first property must have met passes (and graded ones), or it proved nothing."""
    if not OUTCOMES:  # run alone: the property runs first in this file
        test_pass_implies_every_required_measurement_present_and_inside_its_guarded_limits()
    print("verdicts over random histories:", OUTCOMES)
    assert OUTCOMES.get("pass", 0) >= 50 and all(OUTCOMES.get(k, 0) > 0 for k in ("marginal", "fail", "error"))
