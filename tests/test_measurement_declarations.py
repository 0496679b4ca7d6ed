"""Every measurement is declared once (station/decisions/measurements.py) and its readers agree with
the declaration: the built-in limits (unit, label, analysis, what a limit on it means), the readings
(unit), the contract limits of a verified profile, and the field lists of the verdict's record that
the REST models repeat (web/schemas_common.py)."""

from __future__ import annotations

from dataclasses import asdict
from typing import get_args

import pytest

from station.decisions import measurements as M
from station.decisions.limits import default_products
from station.decisions.readings import RunRecord, profile_requirements, run_measurements
from station.decisions.verdicts import CHECK_FIELDS, DECISION_FIELDS, VERDICT_FIELDS, VERDICTS, final_verdict
from web.schemas_common import CheckOut, DecisionFields, DecisionOut, VerdictName


def test_every_built_in_limit_is_on_a_declared_measurement_with_its_unit_label_and_meaning():
    seen = set()
    for spec in default_products().values():
        for lim in [*spec.limits, *(g for grade in spec.grades for g in grade.limits)]:
            d = M.declaration(lim.measurement)
            assert d is not None, lim.measurement
            assert (lim.unit, lim.label, lim.analysis) == (d.unit, d.label, d.analysis), lim.measurement
            if d.kind in ("size", "ratio", "count"):
                assert lim.low is None and lim.high is not None, f"{d.name}: {d.kind} takes an upper limit"
            seen.add(d.name)
    assert {"tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_fs_pct", "bow_mg", "verify_failed_axes"} <= seen


def test_a_verified_profile_requires_the_declared_contract_limits_in_declaration_order():
    req = profile_requirements("thermal", program_verify=True)
    names = [r if isinstance(r, str) else r.measurement for r in req]
    assert names == ["tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_fs_pct", "bow_mg", "lost_samples_pct",
                     "program_crc_match", "compensation_on", "verified_drift_error_fs_pct", "verify_failed_axes"]
    assert [r if isinstance(r, str) else r.measurement for r in profile_requirements("sfem", False)] == \
        ["sfem_bias_mg", "sfem_scale_error_pct", "lost_samples_pct"]
    assert profile_requirements("none", False) == () and profile_requirements("validation", False) == ()
    contract = {r.measurement: (r.low, r.high, r.unit, r.label, r.required) for r in req if not isinstance(r, str)}
    assert contract == {
        "program_crc_match": (1.0, 1.0, "", "readback CRC equal to the written one", True),
        "compensation_on": (1.0, 1.0, "", "on-board compensation on", True),
        "verify_failed_axes": (None, 0.0, "axes", "axes failing the verification", True)}
    for name in contract:
        d = M.declaration(name)
        assert d is not None and d.contract is not None and "program_verify" in d.required_by


def test_every_reading_carries_its_declarations_unit_and_axes():
    axes = {ax: {"tdb_mg_per_c": 0.1, "tdsf_ppm_per_c": -50.0} for ax in "xyz"}
    residual = {ax: {d.name: 0.1 for d in M.in_section("residual")} for ax in "xyz"}
    result = {"axes": axes, "streaming": {"axes": axes}, "residual": {"axes": residual}}
    run = RunRecord("thermal", True, "done", "", result, {"samples_lost": 1}, 100, {"programmed": True, "crc": "ab", "readback_crc": "ab", "comp": 1},
                    {"e_after_fs_pct": {"x": 0.1}, "axes": {"x": {"passed": True}}})
    made = run_measurements(run)
    assert len({m.name for m in made}) >= 15
    for m in made:
        d = M.declaration(m.name)
        assert d is not None and m.unit == d.unit and (m.axis is not None) == d.per_axis, m


def test_the_verdict_records_field_lists_are_the_rest_models():
    v = final_verdict(RunRecord("thermal", False, "faulted", "faulted: link lost"), default_products()["LIS3DSH"])
    assert tuple(v.to_json()) == VERDICT_FIELDS
    # reason_code is no stored field: a live or stored decision derives it from `reason` (causes.reason_code) for the page
    assert set(DecisionOut.model_fields) == {*VERDICT_FIELDS, "attempt", "run_id"}
    assert set(DecisionFields.model_fields) == {*DECISION_FIELDS, "reason_code"}
    assert set(DECISION_FIELDS) <= {*VERDICT_FIELDS, "attempt"}
    assert tuple(CheckOut.model_fields) == CHECK_FIELDS
    assert get_args(VerdictName) == VERDICTS


def test_the_exports_test_numbers_are_the_declarations():
    """Until station/records/export_model.py reads `test_number` itself, its table must agree."""
    from station.records.export_model import TEST_NUMBERS

    assert {d.name: d.test_number for d in M.declared() if d.test_number is not None} == TEST_NUMBERS


def test_a_declaration_is_refused_when_it_contradicts_another():
    d = M.declaration("tdb_mg_per_c")
    assert d is not None and M.declare(d) is d  # the same again: nothing changes
    with pytest.raises(ValueError, match="already declared"):
        M.declare(M.MeasurementDef(**{**asdict(d), "unit": "g/C"}))
    with pytest.raises(ValueError, match="lower-case"):
        M.MeasurementDef("TDB x", "mg/C", "TDB", "TDB", True, "signed", "")
    assert M.declaration("tdb_mg_per_c") == d
