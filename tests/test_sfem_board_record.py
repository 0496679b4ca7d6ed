"""The station's thermal SFEM as the board's version-2 record (station/science/sfem_board_record.py).

Truth, independent of the fit:
- the station's own model (station/science/sfem_thermal.py SfemThermalModel.compensate, float64,
  per parameter) on raw readings, against the board's contract as contracts/sfem_cubic.py states it
  in numpy (`compensate_counts`: the float32 record, the clamp, counts in and out), on raw counts over
  the model's whole range and in every direction: they must agree within APPROX_TOL_MG at 1 g, the
  tolerance this module states for the cubic approximation (measured: < 1e-3 mg on the simulator's
  parts, the float32 rounding of the coefficients included);
- the record's own error report must bound what that comparison finds;
- one coefficient moved (a slope of a11 by 1e-4 / C: 2 mg at 20 C from t_ref) breaks both, so the
  comparison can fail.
Models: random ones drawn by hypothesis (misalignment, non-orthogonality, scale and bias each a cubic
of temperature with the simulator population's magnitudes) and the station's fit of simulated
sfem-24 runs (drivers/sim, 5 temperature steps, -10..65 C).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from contracts.sfem_cubic import SfemCubicRecord
from contracts.sfem_result import SfemResult
from drivers.sim.physics import draw_population
from drivers.sim.profiles import run_profile
from drivers.sim.world import SimWorld
from station.science.sfem_board_record import approximation, cubic_record, thermal_model_of
from station.science.sfem_model import SfemInsufficientData
from station.science.sfem_record import fit_sfem_record
from station.science.sfem_thermal import SfemThermalModel

APPROX_TOL_MG = 0.01  # the record's output error at 1 g over its range (module doc)
UG_PER_LSB = 60.0
DIRECTIONS = np.vstack([np.eye(3), -np.eye(3), np.array([[1, 1, 1], [1, -1, 1], [-1, 1, -1]]) / np.sqrt(3.0)])


def _random_model(rng: np.random.Generator, t_lo: float, t_hi: float) -> SfemThermalModel:
    """Each parameter a cubic of (T - 25): magnitudes of the simulator's population (misalignment and
    non-orthogonality ~1e-2 rad, scale 1 +- 5 %, bias +- 50 mg, thermal slopes like TDSF/TDB)."""
    def cubic(c0: np.ndarray, c1: float, c2: float, c3: float) -> np.ndarray:
        return np.vstack([c0, rng.normal(0, c1, 3), rng.normal(0, c2, 3), rng.normal(0, c3, 3)])

    coef = {"rotvec_rad": cubic(rng.normal(0, 1e-2, 3), 2e-5, 2e-7, 2e-9),
            "alpha": cubic(rng.normal(0, 5e-3, 3), 1e-5, 1e-7, 1e-9),
            "scale": cubic(1.0 + rng.normal(0, 0.05, 3), 3e-4, 3e-6, 3e-8),
            "b": cubic(rng.normal(0, 0.05, 3), 1.4e-3, 1e-5, 1e-7)}
    temps = np.linspace(t_lo, t_hi, 5)
    return SfemThermalModel(3, coef, temps, True, 25.0)


def _board_vs_model(rec: SfemCubicRecord, model: SfemThermalModel, n_temps: int = 97) -> float:
    """Largest |board contract - station model| in mg over the range, every direction, at 1 g."""
    worst = 0.0
    temps = np.linspace(rec.t_lo_c, rec.t_hi_c, n_temps)
    for t in temps:
        p = model.params_at(t)
        # the raw reading that the station's model maps to each unit direction at this temperature
        raw_g = np.linalg.solve(p.A, DIRECTIONS.T).T + p.b
        counts = raw_g / (UG_PER_LSB * 1e-6)
        board_g = rec.compensate_counts(counts, np.full(len(counts), t), UG_PER_LSB) * UG_PER_LSB * 1e-6
        station_g = model.compensate(raw_g, t)
        worst = max(worst, float(np.max(np.abs(board_g - station_g))) * 1e3)
    return worst


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), t_lo=st.floats(-20.0, 20.0), span=st.floats(15.0, 80.0))
def test_random_models_within_the_stated_tolerance(seed, t_lo, span):
    model = _random_model(np.random.default_rng(seed), t_lo, t_lo + span)
    rec, approx = cubic_record(model)
    assert rec == rec.to_f32()  # what the station writes is exactly what the board stores
    assert (rec.t_lo_c, rec.t_hi_c) == pytest.approx(model.temp_range_c, abs=1e-5)
    found = _board_vs_model(rec, model)
    assert found < APPROX_TOL_MG, (found, approx)
    assert approx.max_output_error_mg < APPROX_TOL_MG
    assert found <= approx.max_output_error_mg * 1.5 + 2e-4  # the report bounds what the board does (float32 ulps)


def test_simulated_sfem_runs_and_a_mutated_coefficient():
    truths = draw_population(2, 11)
    logs = run_profile(SimWorld(truths, seed=12), "sfem-24")
    for log in logs:
        fitted = fit_sfem_record(log.time_s, log.acc_g, log.temp_c, log.ref_dir, log.position)
        # the model as it travels (SfemResult JSON) is the science's own object: the same compensation
        model = thermal_model_of(SfemResult.from_json(fitted.to_result().to_json()).thermal)
        assert model is not None and fitted.thermal is not None and model.degree == 3
        u, t = log.acc_g[::97], log.temp_c[::97]
        assert np.allclose(model.compensate(u, t), fitted.thermal.compensate(u, t), rtol=0, atol=1e-12)
        rec, approx = cubic_record(model)
        found = _board_vs_model(rec, model)
        print(f"\n{log.serial}: record {rec.t_lo_c:.1f}..{rec.t_hi_c:.1f} C, CRC {rec.crc32():08X}: board contract vs "
              f"station model max {found * 1e3:.3f} ug at 1 g (reported {approx.max_output_error_mg * 1e3:.3f} ug at "
              f"{approx.worst_temp_c:.1f} C; max |dA| {approx.max_a_error:.2e}, |db| {approx.max_b_error_mg * 1e3:.3f} ug)")
        assert found < APPROX_TOL_MG
        coef = [list(row) for row in rec.coef]
        coef[1][0] += 1e-4  # a11's slope off by 1e-4 / C
        bent = SfemCubicRecord(rec.t_ref_c, rec.t_lo_c, rec.t_hi_c, tuple(map(tuple, coef)))
        moved = _board_vs_model(bent, model)
        reported = approximation(bent, model).max_output_error_mg
        print(f"  a11 slope + 1e-4/C: board vs model {moved:.2f} mg, reported {reported:.2f} mg")
        want = 1e-4 * max(abs(rec.t_hi_c - rec.t_ref_c), abs(rec.t_lo_c - rec.t_ref_c)) * 1e3 * 0.9
        assert moved > want and reported > want
        assert bent.crc32() != rec.crc32()


def test_one_temperature_step_has_no_range_to_write():
    rng = np.random.default_rng(3)
    m = _random_model(rng, 20.0, 40.0)
    one = SfemThermalModel(0, {k: v[:1] for k, v in m.coef.items()}, np.array([25.0]), True, 25.0)
    with pytest.raises(SfemInsufficientData, match="one temperature"):
        cubic_record(one)
    assert thermal_model_of(None) is None and thermal_model_of({"coef": "nonsense"}) is None


def test_verification_on_the_board_contract_passes_and_catches_a_wrong_record():
    """station/daemon/sfem_program.py verify_one on a simulated part: the SFEM steps (25/45/65 C),
    then the plate at the last position while the chamber cools back to 25 C and the "board" sends
    what the contract says it sends (contracts/sfem_cubic.py compensate_counts on the raw counts,
    rounded to counts). The written record passes; a record with one coefficient moved, and a board
    that does not compensate at all, fail."""
    from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX
    from contracts.types import SampleBlock
    from drivers.sim.profiles import Step, run_steps, sfem24_steps
    from station.daemon.sfem_program import VerifyInput, step_sigmas, verify_one

    world = SimWorld(draw_population(1, 21), seed=22)
    ident = world.identity(0)
    pre_steps = sfem24_steps((25.0, 45.0, 65.0))
    pos = pre_steps[-1].position
    cols = run_steps(world, pre_steps)
    acc_g, temp_c = ident.acc_g(cols["acc_counts"][0]), ident.temp_c(cols["temp_counts"][0])
    fitted = fit_sfem_record(cols["time_s"], acc_g, temp_c, GRAVITY_DIRECTIONS[cols["position"]], cols["position"])
    model = thermal_model_of(fitted.to_result().thermal)
    sig = step_sigmas(fitted.to_result())
    rec, approx = cubic_record(model)
    cool = run_steps(world, [Step(2400.0, pos, False, 25.0, 2.0, "verify cool-down")])
    raw, t_counts = cool["acc_counts"][0], cool["temp_counts"][0]
    last = cols["position"] == pos
    last &= cols["time_s"] >= cols["time_s"][last][0]
    pre = SampleBlock(cols["time_s"][last], acc_g[last], temp_c[last])

    def verify(r: SfemCubicRecord | None) -> dict:
        out_counts = np.rint(r.compensate_counts(raw, ident.temp_c(t_counts), ident.ug_per_lsb)) if r is not None else raw
        post = SampleBlock(cool["time_s"], ident.acc_g(out_counts), ident.temp_c(t_counts))
        return verify_one(VerifyInput([(pre, 0, pos), (post, 1, pos)], 1, pos, float(pre.time_s[-1]), 60.0, model,
                                      rec.t_lo_c, rec.t_hi_c, approx.max_output_error_mg, ident.ug_per_lsb / 1e3,
                                      ident.odr_hz, ident.sensor, sig))

    good = verify(rec)
    print(f"\nverified over {good['temp_range_c'][0]:.1f}..{good['temp_range_c'][1]:.1f} C, {good['n_blocks']} blocks:")
    for a in "xyz":
        ax = good["axes"][a]
        print(f"  {a}: rms {ax['residual_rms_mg']:.3f} mg, max {ax['residual_max_mg']:.3f} mg, limits "
              f"{ax['limit_rms_mg']:.3f} / {ax['limit_max_mg']:.3f} mg ({', '.join(f'{k} {v:.3f}' for k, v in ax['terms_mg'].items())})")
    assert good["passed"], good["flags"]
    assert good["temp_range_c"][1] - good["temp_range_c"][0] > 30.0
    coef = [list(row) for row in rec.coef]
    coef[1][4] += 1e-4  # a22's slope: 4 mg at 40 C from t_ref, on the axis that carries 1 g here or not
    coef[1][9] += 1e-4  # and b_x's slope: 1e-4 g/C, 4 mg over the cool-down
    bad = verify(SfemCubicRecord(rec.t_ref_c, rec.t_lo_c, rec.t_hi_c, tuple(map(tuple, coef))))
    print("  record with a22 and b_x slopes moved: " + "; ".join(bad["flags"]))
    assert not bad["passed"] and not bad["axes"]["x"]["passed"]
    raw_out = verify(None)
    assert not raw_out["passed"] and all(not raw_out["axes"][a]["passed"] for a in "xyz")
    assert POSITION_INDEX[SFEM24_LAST] == pos


SFEM24_LAST = "sfem-x315"


def test_the_verdict_of_an_sfem_run_programmed_on_the_board():
    """The station's conventions for program and verify, on an SFEM profile (docs/verdicts.md): the
    contract checks (readback CRC, compensation on, no failing axis) decide, a thermal drift E is not
    required; a failed verification fails, a failed write is error; a board that was not programmed
    (version 1) is judged as the SFEM run alone (the moment passes program_verify False for it)."""
    from contracts.json_safe import plain_json
    from contracts.positions import GRAVITY_DIRECTIONS
    from contracts.run_records import ProgramRecord
    from drivers.sim.profiles import run_steps, sfem24_steps
    from station.decisions.limits import default_products
    from station.decisions.verdicts import RunRecord, final_verdict

    world = SimWorld(draw_population(1, 31), seed=32)
    ident = world.identity(0)
    cols = run_steps(world, sfem24_steps((25.0, 45.0, 65.0)))
    acc_g, temp_c = ident.acc_g(cols["acc_counts"][0]), ident.temp_c(cols["temp_counts"][0])
    result = plain_json(fit_sfem_record(cols["time_s"], acc_g, temp_c, GRAVITY_DIRECTIONS[cols["position"]],
                                        cols["position"]).to_result().to_json())
    spec = default_products()["LIS3DSH"]
    programmed = ProgramRecord(True, method="sfem-cubic", comp=True, attempts=1, readback={
        "crc": "1234ABCD", "readback_crc": "1234ABCD", "readback_identical": True}).to_json()

    def verification(failing: str | None) -> dict:
        return {"kind": "sfem-cubic", "passed": failing is None, "flags": [] if failing is None else [f"{failing}: ..."],
                "temp_range_c": [28.0, 67.0], "axes": {a: {
                    "passed": a != failing, "residual_rms_mg": 3.0 if a == failing else 0.3,
                    "residual_max_mg": 5.0 if a == failing else 0.8, "limit_rms_mg": 1.2, "limit_max_mg": 1.6,
                    "sigma_mg": 0.4} for a in "xyz"}}

    def judge(program, ver, program_verify: bool = True):
        return final_verdict(RunRecord("sfem", program_verify, "done", result=result, link_stats={}, n_samples=len(cols["time_s"]),
                                       program=program, verification=ver), spec)

    base = judge(None, None, program_verify=False)
    good = judge(programmed, verification(None))
    assert base.verdict in ("pass", "marginal") and good.verdict == base.verdict, (base.reasons, good.reasons)
    names = {c.measurement for c in good.checks}
    assert {"program_crc_match", "compensation_on", "verify_failed_axes", "sfem_verified_residual_rms_mg"} <= names
    assert "verified_drift_error_fs_pct" not in names
    bad = judge(programmed, verification("y"))
    assert bad.verdict == "fail", bad.reasons
    assert any("y SFEM on the board: residual rms 3 mg" in r for r in bad.reasons), bad.reasons
    failed_write = ProgramRecord(False, method="sfem-cubic", error_kind="readback_mismatch",
                                 error="read back CRC 00000000 differs from the written 1234ABCD").to_json()
    err = judge(failed_write, None)
    assert err.verdict == "error" and "not programmed" in err.reason, err.reasons
