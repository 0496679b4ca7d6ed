"""Verdicts, grades and guard bands against hand-computed cases (station/decisions/verdicts.py is pure)."""

from __future__ import annotations

import pytest

from station.config import parse_config
from station.decisions.limits import Grade, Limit, ProductSpec, default_products
from contracts.types import AXES, StationError
from station.decisions.verdicts import Measurement, decide, judge, link_measurements, summarize, thermal_measurements

TDSF = Limit(measurement="tdsf_ppm_per_c", low=-500.0, marginal=10.0, unit="ppm/C", label="TDSF")


def spec(**kw) -> ProductSpec:
    base = dict(
        name="test-limits", version="7", sensor="LIS3DSH", guard_sigma=2.0,
        limits=[
            Limit(measurement="tdb_mg_per_c", low=-1.5, high=1.5, unit="mg/C", label="TDB", required=True),
            TDSF,
            Limit(measurement="drift_error_fs_pct", high=1.0, unit="%FS", label="drift E_FS", required=True),
            Limit(measurement="bow_mg", high=3.0, unit="mg", label="curvature (linear model rejected)"),
            Limit(measurement="verified_drift_error_fs_pct", high=1.0, unit="%FS", label="verified E_FS", analysis="any"),
        ],
        grades=[Grade(name="A", tray="tray A", limits=[Limit(measurement="drift_error_fs_pct", high=0.5)]), Grade(name="B")],
    )
    base.update(kw)
    return ProductSpec(**base)


def good(e_fs=(0.3, 0.05), tdsf=-200.0, **over) -> list[Measurement]:
    ms = []
    for ax in AXES:
        ms.append(Measurement("tdb_mg_per_c", over.get(f"tdb_{ax}", 0.5), "mg/C", ax, 0.01))
        ms.append(Measurement("tdsf_ppm_per_c", over.get(f"tdsf_{ax}", tdsf), "ppm/C", ax, 4.0))
        ms.append(Measurement("drift_error_fs_pct", over.get(f"e_{ax}", e_fs[0]), "%FS", ax, e_fs[1]))
        ms.append(Measurement("bow_mg", over.get(f"bow_{ax}", 0.5), "mg", ax, 0.3))
    return ms


# ------------------------------------------------------------------ one value against one limit
def test_value_outside_is_fail_with_value_limit_and_unit():
    c = judge(Measurement("tdsf_ppm_per_c", -612.0, "ppm/C", "z", 5.0), TDSF, 2.0)
    assert c.outcome == "fail"
    assert c.reason == "z TDSF -612 ppm/C, limit -500"


def test_interval_crossing_the_limit_is_marginal_on_either_side():
    # -495 +- 2*4 = [-503, -487] crosses -500
    assert judge(Measurement("tdsf_ppm_per_c", -495.0, "ppm/C", "x", 4.0), TDSF, 2.0).outcome == "marginal"
    # -503 +- 8 = [-511, -495]: the value is outside but the interval reaches back in: still marginal
    c = judge(Measurement("tdsf_ppm_per_c", -503.0, "ppm/C", "x", 4.0), TDSF, 2.0)
    assert c.outcome == "marginal" and "crosses limit -500" in c.reason
    # without an uncertainty the same value is a plain fail
    assert judge(Measurement("tdsf_ppm_per_c", -503.0, "ppm/C", "x", None), TDSF, 2.0).outcome == "fail"


def test_a_model_check_holds_only_on_evidence_and_says_how_much():
    """The curvature limit (evidence_sigma 4): a bow whose interval crosses the limit holds the part
    only when the data reject the linear model; the words say which (docs/verdicts.md "Curvature")."""
    bow = Limit(measurement="bow_mg", high=3.0, unit="mg", label="curvature bow", evidence_sigma=4.0)
    c = judge(Measurement("bow_mg", 1.7, "mg", "x", 0.9), bow, 2.0)  # [-0.1, 3.5] crosses 3, 1.9 sigma
    assert c.outcome == "pass"
    assert c.reason == "x curvature bow 1.7 +-0.9 mg (1 sigma, k=2 band): not significant (1.9 sigma < 4)"
    c = judge(Measurement("bow_mg", 2.5, "mg", "y", 0.5), bow, 2.0)  # [1.5, 3.5] crosses 3, 5 sigma
    assert c.outcome == "marginal"
    assert c.reason == "y curvature bow (linear model rejected, 5.0 sigma) 2.5 +-0.5 mg (1 sigma, k=2 band) crosses limit 3"
    assert judge(Measurement("bow_mg", 5.0, "mg", "z", 0.5), bow, 2.0).outcome == "fail"  # [4, 6] over 3
    assert judge(Measurement("bow_mg", 1.0, "mg", "z", 0.25), bow, 2.0).outcome == "pass"  # [0.5, 1.5] inside
    # the same numbers against a plain guard-banded limit hold the first part
    plain = bow.model_copy(update={"evidence_sigma": 0.0})
    assert judge(Measurement("bow_mg", 1.7, "mg", "x", 0.9), plain, 2.0).outcome == "marginal"


def test_marginal_band_inside_the_limit():
    # -485 +- 8 -> lowest -493, inside -500 but within the 10 ppm/C band (-490)
    c = judge(Measurement("tdsf_ppm_per_c", -485.0, "ppm/C", "y", 4.0), TDSF, 2.0)
    assert c.outcome == "marginal" and "within 10 of limit -500" in c.reason
    # -480 +- 8 -> lowest -488: clear of the band
    assert judge(Measurement("tdsf_ppm_per_c", -480.0, "ppm/C", "y", 4.0), TDSF, 2.0).outcome == "pass"


def test_missing_value_is_error():
    assert judge(Measurement("tdsf_ppm_per_c", None, "ppm/C", "y"), TDSF, 2.0).outcome == "error"


# ------------------------------------------------------------------ a DUT
def test_pass_and_grades_follow_the_intervals():
    v = decide(good(e_fs=(0.3, 0.05)), spec())  # E_FS interval [0.2, 0.4] inside grade A's 0.5
    assert (v.verdict, v.grade, v.tray) == ("pass", "A", "tray A")
    assert v.reason == "all limits met" and v.limits_name == "test-limits" and v.limits_version == "7"
    v = decide(good(e_fs=(0.45, 0.05)), spec())  # [0.35, 0.55] crosses grade A's 0.5: grade B
    assert (v.verdict, v.grade, v.tray) == ("pass", "B", "grade B")


def test_uncertainty_crossing_a_limit_makes_the_dut_marginal():
    v = decide(good(e_z=0.97), spec())  # 0.97 +- 0.10 crosses 1.0
    assert (v.verdict, v.grade) == ("marginal", "hold")
    assert v.reasons == ["z drift E_FS 0.97 +-0.05 %FS (1 sigma, k=2 band) crosses limit 1"]


def test_every_failing_measurement_is_named():
    v = decide(good(tdsf_z=-612.0, bow_x=4.6), spec())
    assert (v.verdict, v.grade, v.tray) == ("fail", "reject", "reject")
    assert "z TDSF -612 ppm/C, limit -500" in v.reasons
    assert "x curvature (linear model rejected) 4.6 mg, limit 3" in v.reasons
    fails = [c for c in v.checks if c.outcome == "fail"]
    assert {(c.measurement, c.axis) for c in fails} == {("tdsf_ppm_per_c", "z"), ("bow_mg", "x")}
    j = v.to_json()
    assert {f["measurement"] for f in j["failures"]} == {"tdsf_ppm_per_c", "bow_mg"}


def test_fail_outranks_marginal_in_the_reasons():
    v = decide(good(tdsf_z=-612.0, e_y=0.97), spec())
    assert v.verdict == "fail"
    assert v.reasons[0].startswith("z TDSF") and any("crosses" in r for r in v.reasons[1:])


@pytest.mark.parametrize("state", ["faulted", "interrupted", "connecting", "running"])
def test_a_faulted_or_incomplete_dut_is_error_never_pass(state):
    v = decide(good(), spec(), state=state, fault_reason="serial /dev/pts/3: link lost" if state == "faulted" else "")
    assert (v.verdict, v.grade, v.tray) == ("error", "retest", "retest")
    assert v.reasons and (state in v.reasons[0] or "link lost" in v.reasons[0])


def test_missing_required_measurement_is_error():
    ms = [m for m in good() if not (m.name == "drift_error_fs_pct" and m.axis == "y")]
    v = decide(ms, spec())
    assert v.verdict == "error" and v.reasons == ["y drift E_FS not measured"]
    assert decide([], spec()).verdict == "error"
    assert decide(good(), None).verdict == "error"


def test_optional_verified_drift_error_is_judged_when_present():
    assert decide(good(), spec()).verdict == "pass"  # absent: not required
    v = decide(good() + [Measurement("verified_drift_error_fs_pct", 1.4, "%FS", "z", 0.05)], spec())
    assert v.verdict == "fail" and v.reasons == ["z verified E_FS 1.4 %FS, limit 1"]


def test_limits_of_another_analysis_are_not_applied():
    s = spec(limits=[*spec().limits, Limit(measurement="sfem_bias_mg", low=-100, high=100, required=True, analysis="sfem")])
    assert decide(good(), s, analysis="thermal").verdict == "pass"
    assert decide(good(), s, analysis="sfem").verdict == "error"  # required there and missing


# ------------------------------------------------------------------ measurement extraction
def test_thermal_measurements_from_a_result():
    axes = {ax: {"tdb_mg_per_c": 0.5, "tdsf_ppm_per_c": -100.0, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": 3.0}
            for ax in AXES}
    stream = {ax: {"tdb_mg_per_c": 0.62, "tdsf_ppm_per_c": -40.0} for ax in AXES}
    residual = {ax: {"drift_error_fs_pct": 0.2, "drift_error_fs_sigma_pct": 0.03, "drift_error_mg": 4.0, "bow_mg": 1.0,
                     "bow_sigma_mg": 0.2, "ramp_residual_rms_mg": 0.3, "noise_ug_per_sqrt_hz": 400.0} for ax in AXES}
    ms = thermal_measurements({"axes": axes, "streaming": {"axes": stream}, "residual": {"axes": residual}})
    by = {(m.name, m.axis): m for m in ms}
    assert by[("tdsf_ppm_per_c", "y")].value == -100.0 and by[("tdsf_ppm_per_c", "y")].sigma == 3.0
    assert by[("fit_agreement_tdb_mg_per_c", "z")].value == pytest.approx(0.12)
    assert by[("fit_agreement_tdsf_ppm_per_c", "x")].value == pytest.approx(60.0)
    assert by[("drift_error_fs_pct", "x")].sigma == 0.03
    assert thermal_measurements(None) == []


def test_link_measurements():
    ms = {m.name: m.value for m in link_measurements({"samples_lost": 10, "frames_bad_checksum": 3, "frames_malformed": 2,
                                                      "bytes_skipped": 999, "errors_reported": 1}, 990)}
    assert ms == {"link_errors": 6.0, "lost_samples_pct": pytest.approx(1.0)}


def test_summary_counts():
    s = summarize([{"verdict": "pass", "grade": "A"}, {"verdict": "fail", "grade": "reject"}, None,
                   {"verdict": "pass", "grade": "B"}, {"verdict": "error", "grade": "retest"}])
    assert s["judged"] == 4 and s["verdicts"] == {"pass": 2, "marginal": 0, "fail": 1, "error": 1}
    assert s["grades"] == {"A": 1, "B": 1, "reject": 1, "retest": 1}


# ------------------------------------------------------------------ limits as config data
def _cfg(products: dict | None = None) -> dict:
    d = {"slots": [{"name": "s1", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1}}
    if products is not None:
        d["products"] = products
    return d


def test_builtin_products_and_site_override():
    cfg = parse_config(_cfg(), "t")
    assert cfg.product_for("LIS3DSH").name == "LIS3DSH-default"
    assert cfg.product_for("adxl355").name == "ADXL355-default"
    assert cfg.product_for("BMI088") is None
    site = {"LIS3DSH": {"version": "2026-11", "sensor": "LIS3DSH", "limits": [
        {"measurement": "tdsf_ppm_per_c", "low": -400, "unit": "ppm/C", "label": "TDSF"}]},
        "board-x": {"sensor": "LIS3DSH", "part_numbers": ["PN-42"], "limits": [
            {"measurement": "tdb_mg_per_c", "low": -1, "high": 1}]}}
    cfg = parse_config(_cfg(site), "t")
    p = cfg.product_for("LIS3DSH")
    assert (p.name, p.version) == ("LIS3DSH", "2026-11")
    assert cfg.product_for("LIS3DSH", "PN-42").name == "board-x"
    snap = cfg.snapshot()["products"]  # stored with every batch: the site's sets and the built-ins in force
    assert snap["LIS3DSH"]["version"] == "2026-11" and snap["ADXL355"]["name"] == "ADXL355-default"
    # a site product under its own key wins the sensor match over the built-in
    cfg = parse_config(_cfg({"line-2": {"sensor": "LIS3DSH", "limits": [{"measurement": "tdb_mg_per_c", "high": 1}]}}), "t")
    assert cfg.product_for("LIS3DSH").name == "line-2" and cfg.product_for("ADXL355").name == "ADXL355-default"


def test_bad_limit_is_a_config_error():
    with pytest.raises(StationError, match=r"products\.p\.limits\[0\].*low 2 > high 1"):
        parse_config(_cfg({"p": {"sensor": "LIS3DSH", "limits": [{"measurement": "tdb_mg_per_c", "low": 2, "high": 1}]}}), "t")


def test_default_limits_cover_the_thermal_measurements():
    for p in default_products().values():
        names = {lim.measurement for lim in p.limits}
        assert {"tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_fs_pct", "bow_mg", "noise_ug_per_sqrt_hz",
                "lost_samples_pct", "link_errors", "fit_agreement_tdb_mg_per_c", "sfem_bias_mg"} <= names


def test_systematic_uncertainty_widens_the_guard_band():
    lim = Limit(measurement="tdb_mg_per_c", high=1.0, unit="mg/C", label="TDB", u_sys=0.003)
    # 0.995 +- 2 * hypot(0.0004, 0.003) = 0.995 +- 0.00605: crosses 1.0
    c = judge(Measurement("tdb_mg_per_c", 0.995, "mg/C", "x", 0.0004), lim, 2.0)
    assert c.outcome == "marginal" and c.sigma == pytest.approx(0.0030265, rel=1e-4)
    # the fit's sigma alone (0.995 + 0.0008) would not reach it
    assert judge(Measurement("tdb_mg_per_c", 0.995, "mg/C", "x", 0.0004), lim.model_copy(update={"u_sys": 0.0}), 2.0).outcome == "pass"


def test_sfem_measurements_and_limits():
    from station.decisions.verdicts import sfem_measurements

    fit = {"temp_c": 26.0, "bias": [0.012, -0.130, 0.0], "bias_sigma": [1e-4, 1e-4, 1e-4], "scale": [1.02, 0.97, 1.001],
           "scale_sigma": [1e-4, 1e-4, 1e-4]}
    ms = sfem_measurements({"shape": "sfem-record/1", "t_ref_c": 25.0, "steps": [fit]})  # contracts/sfem_result.py
    by = {(m.name, m.axis): m for m in ms}
    assert by[("sfem_bias_mg", "y")].value == pytest.approx(-130.0) and by[("sfem_bias_mg", "y")].sigma == pytest.approx(0.1)
    assert by[("sfem_scale_error_pct", "y")].value == pytest.approx(3.0)
    v = decide(ms, default_products()["LIS3DSH"], analysis="sfem")
    assert v.verdict == "fail" and v.reasons == ["y bias -130 mg, limit -100"]


def test_operator_reason_shows_the_worst_three():
    v = decide(good(tdsf_x=-612.0, tdsf_y=-700.0, tdsf_z=-800.0, bow_x=5.0), spec())
    assert len(v.reasons) == 4 and v.reason.endswith("; +1 more") and v.reason.count(";") == 3


SITE_TOML = """
[[slots]]
name = "s1"
serial = "/dev/ttyACM0"

[lamp]
unit = 1
tcp = { host = "127.0.0.1" }

[products.LIS3DSH]
name = "LIS3DSH-line2"
version = "2026-11-23"
sensor = "LIS3DSH"
operating_range_c = 60
guard_sigma = 2

[[products.LIS3DSH.limits]]
measurement = "tdsf_ppm_per_c"
low = -450
marginal = 10
unit = "ppm/C"
label = "TDSF"
required = true
u_sys = 2

[[products.LIS3DSH.limits]]
measurement = "drift_error_fs_pct"
high = 1.0
unit = "%FS"
label = "drift E_FS"
required = true

[[products.LIS3DSH.grades]]
name = "A"
tray = "A (left)"
limits = [{ measurement = "drift_error_fs_pct", high = 0.5 }]

[[products.LIS3DSH.grades]]
name = "B"
tray = "B (right)"
"""


def test_limits_from_a_site_toml(tmp_path):
    from station.config import load_config

    p = tmp_path / "station.toml"
    p.write_text(SITE_TOML)
    spec = load_config(p).product_for("LIS3DSH")
    assert (spec.name, spec.version, spec.operating_range_c) == ("LIS3DSH-line2", "2026-11-23", 60.0)
    ms = [Measurement("tdsf_ppm_per_c", -300.0, "ppm/C", ax, 1.0) for ax in AXES]
    ms += [Measurement("drift_error_fs_pct", 0.7, "%FS", ax, 0.05) for ax in AXES]
    v = decide(ms, spec)
    assert (v.verdict, v.grade, v.tray) == ("pass", "B", "B (right)")


# ------------------------------------------------------------------ grades (issue 21)
def test_a_grade_uses_the_verdicts_guard_band_with_the_specs_systematic_term():
    # TDB 0.9 with u_sys 0.2: the interval 0.9 +- 2 x 0.2 reaches 1.3, over grade A's 1.0 -> not A
    s = spec(limits=[Limit(measurement="tdb_mg_per_c", low=-1.5, high=1.5, u_sys=0.2, required=True)],
             grades=[Grade(name="A", limits=[Limit(measurement="tdb_mg_per_c", low=-1.0, high=1.0)]), Grade(name="B")])
    ms = [Measurement("tdb_mg_per_c", 0.9, "mg/C", ax, 0.0) for ax in AXES]
    assert decide(ms, s).grade == "B"
    ms = [Measurement("tdb_mg_per_c", 0.55, "mg/C", ax, 0.0) for ax in AXES]  # 0.55 + 0.4 < 1.0
    assert decide(ms, s).grade == "A"


def test_a_grade_needs_every_axis():
    v = decide(good(e_x=0.2, e_y=0.2, e_z=0.6, e_fs=(0.2, 0.01)), spec())
    assert (v.verdict, v.grade) == ("pass", "B")  # z misses grade A's 0.5
    v = decide(good(e_fs=(0.2, 0.01)), spec())
    assert (v.verdict, v.grade) == ("pass", "A")


def test_meeting_no_grade_is_its_own_outcome():
    s = spec(grades=[Grade(name="A", limits=[Limit(measurement="drift_error_fs_pct", high=0.5)]),
                     Grade(name="B", limits=[Limit(measurement="drift_error_fs_pct", high=0.7)])])
    v = decide(good(e_fs=(0.8, 0.01)), s)  # inside the spec's 1.0, outside every grade
    assert (v.verdict, v.grade, v.tray) == ("fail", "none", "reject (no grade)")
    assert v.reason.startswith("meets no grade: A:") and "B:" in v.reason


def test_numpy_scalars_are_measurements():
    import numpy as np

    ms = [Measurement(m.name, np.float32(m.value), m.unit, m.axis, np.float64(m.sigma)) for m in good()]
    v = decide(ms, spec())
    assert v.verdict == "pass", v.reasons
