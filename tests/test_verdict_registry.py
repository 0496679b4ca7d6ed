"""A verdict check is one registered object (station/decisions/checks.py).

The example check here, "max |TDB| of all axes below a test-only limit", is written and registered
in this file only: with it a run that passes every limit of its product fails, in the check's own
words, and the records word its measurement; without it the same run passes. No other file of the
station knows it. Likewise a new thermal figure is one declaration (station/decisions/measurements.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from station.decisions import checks
from station.decisions.checks import Finding, RunView, registered
from station.decisions.judging import judge
from station.decisions.limits import Limit, ProductSpec, default_products
from station.decisions.measurements import TDB, MeasurementDef, declaration, declared_for_now
from station.decisions.verdicts import RunRecord, final_verdict, run_measurements
from station.records import parameter_names

AXES = ("x", "y", "z")
TDB_MG_PER_C = {"x": 0.21, "y": -0.62, "z": 0.33}


def thermal_result(**residual_extra: float) -> dict[str, object]:
    """A LIS3DSH part inside every built-in limit (grade A)."""
    return {
        "axes": {ax: {"tdb_mg_per_c": TDB_MG_PER_C[ax], "tdb_sigma_mg_per_c": 0.01, "tdsf_ppm_per_c": -150.0,
                      "tdsf_sigma_ppm_per_c": 4.0} for ax in AXES},
        "streaming": {"axes": {ax: {"tdb_mg_per_c": TDB_MG_PER_C[ax] + 0.01, "tdsf_ppm_per_c": -140.0} for ax in AXES}},
        "residual": {"axes": {ax: {"drift_error_fs_pct": 0.3, "drift_error_fs_sigma_pct": 0.02, "drift_error_mg": 6.0,
                                   "drift_error_sigma_mg": 0.4, "bow_mg": 0.2, "bow_sigma_mg": 0.2,
                                   "ramp_residual_rms_mg": 0.3, "noise_ug_per_sqrt_hz": 350.0, **residual_extra}
                              for ax in AXES}},
    }


def run(**residual_extra: float) -> RunRecord:
    return RunRecord("thermal", False, "done", "", thermal_result(**residual_extra), {"samples_lost": 0}, 2000)


SPEC = default_products()["LIS3DSH"]


# ---- the example check: one class, one registration -------------------------------------------
MAX_ABS_TDB = MeasurementDef(
    "max_abs_tdb_mg_per_c", "mg/C", "max |TDB| of all axes", "max |TDB| (all axes)", False, "size",
    "the 1-sigma of the axis with the largest |TDB|", "largest |TDB| of x, y, z", analysis="any")


@dataclass(frozen=True)
class MaxAbsTdb:
    """The largest |TDB| of the three axes against a limit of its own (the part's worst axis)."""

    limit_mg_per_c: float
    name: str = "max_abs_tdb"
    needs: frozenset[str] | None = frozenset({TDB.name})
    declares: tuple[MeasurementDef, ...] = (MAX_ABS_TDB,)

    def apply(self, run: RunView, spec: ProductSpec) -> Finding:
        assert {m.name for m in run.measurements} == {TDB.name}  # it sees what it needs, nothing else
        measured = [m for m in run.measurements if m.value is not None]
        if not measured:
            return None  # the product's own TDB requirement says "not measured"
        worst = max(measured, key=lambda m: abs(m.value or 0.0))
        limit = Limit(measurement=MAX_ABS_TDB.name, high=self.limit_mg_per_c, unit=MAX_ABS_TDB.unit,
                      label=MAX_ABS_TDB.label, analysis="any")
        return judge(MAX_ABS_TDB.measured(abs(worst.value or 0.0), sigma=worst.sigma), limit, spec.guard_sigma)


def test_without_the_check_the_run_passes():
    v = final_verdict(run(), SPEC)
    assert (v.verdict, v.grade, v.reason) == ("pass", "A", "all limits met")
    assert "max_abs_tdb" not in [c.name for c in checks.verdict_checks()]
    assert all(c.measurement != MAX_ABS_TDB.name for c in v.checks)


def test_a_registered_check_fails_the_run_in_its_own_words_and_the_records_word_it():
    with registered(MaxAbsTdb(limit_mg_per_c=0.5)):
        v = final_verdict(run(), SPEC)
        assert (v.verdict, v.grade, v.tray) == ("fail", "reject", SPEC.reject_tray)
        assert v.reasons == ["max |TDB| of all axes 0.62 mg/C, limit 0.5"]
        mine = [c for c in v.to_json()["checks"] if c["measurement"] == MAX_ABS_TDB.name]
        assert mine == [{"measurement": MAX_ABS_TDB.name, "axis": None, "value": pytest.approx(0.62),
                         "sigma": pytest.approx(0.01), "unit": "mg/C", "low": None, "high": 0.5, "outcome": "fail",
                         "reason": "max |TDB| of all axes 0.62 mg/C, limit 0.5"}]
        # the records read its declaration (SPC, Pareto), as they read the station's own
        assert parameter_names.label(MAX_ABS_TDB.name) == "max |TDB| (all axes) (mg/°C)"
        with pytest.raises(ValueError, match="already registered"):  # one check per name
            checks.register(MaxAbsTdb(limit_mg_per_c=1.0))
    # a looser limit: the check passes and is on the list of checks like any other
    with registered(MaxAbsTdb(limit_mg_per_c=1.0)):
        v = final_verdict(run(), SPEC)
        assert (v.verdict, v.grade) == ("pass", "A")
        assert [c.outcome for c in v.checks if c.measurement == MAX_ABS_TDB.name] == ["pass"]
    # unregistered: the same run passes again, and its measurement is no longer declared
    assert final_verdict(run(), SPEC).verdict == "pass"
    assert declaration(MAX_ABS_TDB.name) is None
    assert parameter_names.label(MAX_ABS_TDB.name, "mg/C") == "max abs tdb mg per c (mg/°C)"


def test_the_built_in_checks_are_registered_objects_too():
    names = [c.name for c in checks.verdict_checks()]
    assert names[:2] == ["spec_limits", "sfem_fit_mark"]
    # the product's limits are one check: without it nothing is judged but what the others find
    only_mark = [c for c in checks.verdict_checks() if c.name != "spec_limits"]
    view = RunView(tuple(run_measurements(run())), "thermal")
    assert checks.run_checks(view, SPEC, only_mark) == ([], [])
    found, marks = checks.run_checks(view, SPEC)
    assert marks == [] and {c.outcome for c in found} == {"pass"} and len(found) > 20


def test_a_thermal_figure_is_one_declaration():
    """Declared with where the residual report holds it and that a thermal profile requires it: read,
    required and worded with no other change (a product limits it like any other)."""
    self_heating = MeasurementDef("self_heating_mg", "mg", "self-heating", "self-heating offset", True, "size",
                                  "none: judged on its value", "residual report", section="residual",
                                  required_by=("thermal",))
    with declared_for_now(self_heating):
        v = final_verdict(run(), SPEC)
        assert v.verdict == "error" and v.reasons == [f"{ax} self_heating_mg not measured" for ax in AXES]
        good = run(self_heating_mg=0.4)
        assert [(m.axis, m.value, m.unit) for m in run_measurements(good) if m.name == "self_heating_mg"] == \
            [(ax, 0.4, "mg") for ax in AXES]
        assert final_verdict(good, SPEC).verdict == "pass"
        limited = SPEC.model_copy(update={"limits": [*SPEC.limits, Limit(measurement="self_heating_mg", high=0.3,
                                                                          label=self_heating.label, unit="mg")]})
        assert final_verdict(good, limited).reasons == [f"{ax} self-heating 0.4 mg, limit 0.3" for ax in AXES]
        assert parameter_names.label("self_heating_mg:z") == "self-heating offset z (mg)"
    assert final_verdict(run(), SPEC).verdict == "pass"  # undeclared: not required any more
