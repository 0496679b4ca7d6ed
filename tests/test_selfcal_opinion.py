"""The board's own calibrator as a second opinion (issue 42): the comparison's science and its check.

Truth, independent of the code under test:
- a hand-made board: two orientations (+a, -a g on an axis) with two segments each, TDSF exactly 0,
  white noise only. Then TDB = (TD_1 + TD_2) / 2 and TDSF = (TD_1 - TD_2) / (2a), each TD_i the
  difference of two segment means over dT, so by hand sigma_TDB = s / (dT sqrt n) and
  sigma_TDSF = s / (a dT sqrt n) (s the per-sample noise, n samples per segment); hypothesis draws dT,
  n, s and a and the station's derivative-based sigma must give exactly these.
- the simulator's own parts (drivers/sim, correlated noise: random walk and flicker per the sensor
  class, at 0.4x, 1x and 3x its level): the board's estimate (martinez2022 3.3 on its segments)
  against the simulator's true TDB/TDSF, err / sigma over every axis. Its RMS must be near 1 and at
  most a few percent may lie beyond 2 sigma; the same estimate with a white-noise-only sigma (what
  sigma/sqrt(n) of a segment mean would give) is off several times: that is the mutation that shows
  the bias wander is in.
- the check's outcomes by construction: a board that reports the station's own figures agrees; the
  same board with its TDB moved by 5 combined sigmas fails `board_selfcal_agrees` naming that figure
  with both values; a board without a calibrator is not applicable (never a fail); a capable board
  whose $SCRR failed is error (never a pass), through the verdict itself.

`python -m pytest tests/test_selfcal_opinion.py -s` prints the coverage figures.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from contracts.json_safe import plain_json
from contracts.selfcal_opinion import BoardSegment, BoardSelfCalReading, SelfCalOpinion
from contracts.types import AXES, AxisThermal, SampleBlock, Segment
from drivers.sim.physics import draw_population, noise_model
from drivers.sim.profiles import fast_thermal_steps, run_steps
from drivers.sim.world import SimWorld
from station.decisions.limits import default_products
from station.decisions.verdicts import RunRecord, final_verdict
from station.science.bias_wander import NO_WANDER
from station.science.selfcal_compare import (K_AGREE, PartNoiseModel, board_segments, compare, estimator_sigmas,
                                             part_noise_model)
from station.science.thermal_calibration import calibrate

ODR = 3.125


def _seg(i: int, o: int, t_end_s: float, acc: tuple[float, float, float], temp: float, n: int) -> Segment:
    return Segment(i, o, n, t_end_s - (n - 1) / ODR, t_end_s, acc, (0.0, 0.0, 0.0), temp, 0.0)


def _hand_board(d_t: float, n: int, a: float, tdb_g_per_c: float = 1e-3) -> list[Segment]:
    """Two orientations, +a and -a g on every axis, ambient 25 C and hot 25 + d_t, TDSF 0."""
    segs = []
    for o, sign in enumerate((1.0, -1.0)):
        for k, temp in enumerate((25.0, 25.0 + d_t)):
            acc = sign * a + tdb_g_per_c * (temp - 25.0)
            segs.append(_seg(2 * o + k, o, 1000.0 * (2 * o + k + 1), (acc, acc, acc), temp, n))
    return segs


@settings(max_examples=25, deadline=None)
@given(d_t=st.floats(15.0, 40.0), n=st.integers(200, 3000), s_mg=st.floats(0.05, 5.0), a=st.floats(0.4, 1.0))
def test_white_noise_sigma_is_the_hand_formula(d_t, n, s_mg, a):
    s = s_mg * 1e-3
    noise = PartNoiseModel((s, s, s), NO_WANDER, 0.0, 0.0, "hand-made")
    sig, terms = estimator_sigmas(_hand_board(d_t, n, a), noise)
    want_tdb = s / (d_t * math.sqrt(n)) * 1e3  # mg/C
    want_tdsf = s / (a * d_t * math.sqrt(n)) * 1e6  # ppm/C
    for k in range(3):
        assert sig[0, k] == pytest.approx(want_tdb, rel=1e-5)
        assert sig[1, k] == pytest.approx(want_tdsf, rel=1e-5)
        assert terms["tdb_mg_per_c"][AXES[k]]["wander"] == 0.0


def test_board_clock_is_unwrapped_in_the_order_of_saving():
    wrap = 1 << 32
    frames = [BoardSegment(0, 0, wrap - 2_000_000, (0.5, 0.5, 0.5), 25.0, 1000),
              BoardSegment(1, 0, 3_000_000, (0.5, 0.5, 0.5), 50.0, 1000),  # the 32-bit clock wrapped
              BoardSegment(2, 1, 900_000_000, (-0.5, -0.5, -0.5), 50.0, 1000)]
    segs = board_segments(list(reversed(frames)), ODR)
    assert [s.index for s in segs] == [0, 1, 2]
    assert segs[1].t_end_s - segs[0].t_end_s == pytest.approx(5.0)
    assert segs[2].t_end_s - segs[1].t_end_s == pytest.approx(897.0)
    assert segs[0].t_end_s - segs[0].t_start_s == pytest.approx(999 / ODR)


def _simulated(scale: float, seed: int, n_duts: int = 6):
    base = noise_model("realistic")
    nm = replace(base, name=f"x{scale:g}", bias_rw_g_per_sqrt_s=base.bias_rw_g_per_sqrt_s * scale,
                 flicker_g=base.flicker_g * scale, white_scale=scale)
    truths = draw_population(n_duts, 300 + seed)
    world = SimWorld(truths, seed=400 + seed, noise=nm)
    cols = run_steps(world, fast_thermal_steps())
    for i in range(world.n_duts):
        ident = world.identity(i)
        blk = SampleBlock(cols["time_s"], ident.acc_g(cols["acc_counts"][i]), ident.temp_c(cols["temp_counts"][i]))
        yield truths[i], ident, calibrate(blk)


def _segments(res: dict) -> list[Segment]:
    return [Segment(**{**s, "acc_mean_g": tuple(s["acc_mean_g"]), "acc_std_g": tuple(s["acc_std_g"])})
            for s in res["segments"]]


@pytest.mark.parametrize("scale", [0.4, 1.0, 3.0])
def test_board_sigma_covers_its_error_under_correlated_noise(scale):
    """The board's estimator (two segment means per orientation and temperature) against the
    simulator's truth, on parts whose bias wanders (module doc)."""
    z, z_white = [], []
    for seed in range(3):
        for truth, ident, res in _simulated(scale, seed):
            segs = _segments(res)
            noise = part_noise_model(res["uncertainty"], segs, ident.odr_hz, ident.sensor)
            sig, _ = estimator_sigmas(segs, noise)
            white, _ = estimator_sigmas(segs, replace(noise, wander=NO_WANDER, temp_quantum_c=0.0))
            board = res["streaming"]["axes"]  # the same end-of-test computation the board runs
            for k, a in enumerate(AXES):
                e = board[a]["tdb_mg_per_c"] - truth.tdb_mg_per_c[k]
                z.append(e / sig[0, k])
                z_white.append(e / white[0, k])
                if not board[a]["tdsf_clamped"] and truth.tdsf_ppm_per_c[k] < -30.0:  # a clamped 0 is no estimate
                    e = board[a]["tdsf_ppm_per_c"] - truth.tdsf_ppm_per_c[k]
                    z.append(e / sig[1, k])
                    z_white.append(e / white[1, k])
    z_arr, zw = np.array(z), np.array(z_white)
    rms, cover, rms_white = float(np.sqrt(np.mean(z_arr ** 2))), float(np.mean(np.abs(z_arr) <= 2.0)), \
        float(np.sqrt(np.mean(zw ** 2)))
    print(f"\nnoise x{scale:g}: {len(z_arr)} figures, RMS(err/u) {rms:.2f}, within 2u {cover:.1%}, max "
          f"{np.max(np.abs(z_arr)):.2f}; white-only sigma: RMS {rms_white:.2f}")
    assert 0.6 < rms < 1.4, rms
    assert cover >= 0.9, cover
    assert rms_white > 3.0, rms_white  # the mutation: without the wander the band is several times too narrow


def _station_and_board():
    truth, ident, res = next(_simulated(1.0, 7, n_duts=1))
    segs = _segments(res)
    st_axes = {a: AxisThermal(**{k: res["axes"][a][k] for k in ("tdb_mg_per_c", "tdsf_ppm_per_c", "tdb_sigma_mg_per_c",
                                                                 "tdsf_sigma_ppm_per_c", "tdsf_clamped")}) for a in AXES}
    board = res["streaming"]["axes"]
    reading = BoardSelfCalReading(True, tuple(board[a]["tdb_mg_per_c"] for a in AXES),
                                  tuple(board[a]["tdsf_ppm_per_c"] for a in AXES), len(segs),
                                  tuple(board[a]["tdsf_clamped"] for a in AXES),
                                  tuple(BoardSegment(s.index, s.orientation, int(round(s.t_end_s * 1e6)) % (1 << 32),
                                                     s.acc_mean_g, s.temp_mean_c, s.n_samples) for s in segs))
    return ident, res, segs, st_axes, reading


def _judge(opinion: SelfCalOpinion | dict | None, result: dict | None = None):
    """The verdict of a done thermal run with this opinion (and the station's result, when given)."""
    run = RunRecord("thermal", False, "done", result=None if result is None else plain_json(result), link_stats={},
                    n_samples=int(result["n_samples"]) if result else 0,
                    board_selfcal=None if opinion is None else (opinion if isinstance(opinion, dict) else opinion.to_json()))
    return final_verdict(run, default_products()["LIS3DSH"])


def _named(v, name: str = "board_selfcal_agrees"):
    return [c for c in v.checks if c.measurement == name]


def test_the_board_that_agrees_and_the_one_that_does_not():
    ident, res, segs, st_axes, reading = _station_and_board()
    op = compare(reading, st_axes, res["uncertainty"], segs, ident.odr_hz, ident.sensor)
    assert op.applicable and op.error is None and op.agrees, op
    assert SelfCalOpinion.from_json(plain_json(op.to_json())) == op  # the stored JSON reads back the same
    for r in op.rows:
        print(f"{r.axis} {r.label}: board {r.board:+.4f} station {r.station:+.4f} {r.unit} "
              f"(u board {r.u_board:.4f}, station {r.u_station:.4f}, combined {r.u_combined:.4f}, "
              f"from its segments {r.board_from_segments:+.4f})")
        assert r.board_from_segments == pytest.approx(r.board, abs=1e-9)  # its own segments give its figure
    good = _judge(op, res)
    [agree] = _named(good)
    assert agree.outcome == "pass" and agree.value == 1.0 and good.verdict in ("pass", "marginal"), good.reasons
    # the same board with its x TDB off by 5 combined sigmas (a calibrator that disagrees)
    x_tdb = next(r for r in op.rows if r.axis == "x" and r.figure == "tdb_mg_per_c")
    skew = 5.0 * x_tdb.u_combined
    bad = replace(reading, tdb_mg_per_c=(reading.tdb_mg_per_c[0] + skew, *reading.tdb_mg_per_c[1:]))
    op_bad = compare(bad, st_axes, res["uncertainty"], segs, ident.odr_hz, ident.sensor)
    assert not op_bad.agrees
    assert [(r.axis, r.figure) for r in op_bad.rows if not r.agrees] == [("x", "tdb_mg_per_c")]
    v = _judge(op_bad, res)
    [agree] = _named(v)
    assert v.verdict == "fail" and agree.outcome == "fail" and agree.value == 0.0
    assert "x TDB board" in v.reason and "station" in v.reason, v.reason
    # the figures side by side per axis are on the verdict, beside the check that decides
    rows = _named(v, "board_selfcal_tdb_mg_per_c")
    assert {c.axis for c in rows} == set(AXES)
    row_x = next(c for c in rows if c.axis == "x")
    assert row_x.value == pytest.approx(bad.tdb_mg_per_c[0]) and row_x.outcome == "fail"
    assert row_x.low < x_tdb.station < row_x.high
    # just inside the band: still agrees (K_AGREE combined sigmas)
    near = replace(reading, tdb_mg_per_c=(x_tdb.station + 0.9 * K_AGREE * x_tdb.u_combined, *reading.tdb_mg_per_c[1:]))
    assert compare(near, st_axes, res["uncertainty"], segs, ident.odr_hz, ident.sensor).agrees


def test_without_a_calibrator_not_applicable_and_a_failed_read_is_error():
    ident, res, segs, st_axes, reading = _station_and_board()
    none = compare(BoardSelfCalReading(False, note="caps: none"), st_axes, res["uncertainty"], segs, ident.odr_hz)
    v = _judge(none, res)
    [mark] = _named(v)
    assert not none.applicable and mark.outcome == "pass" and "not applicable" in mark.reason
    assert (v.verdict, v.reasons) == (_judge(None, res).verdict, _judge(None, res).reasons)  # nothing else changes
    failed = compare(BoardSelfCalReading(True, error="$SCRR failed: E,SCRR no result: no segments"), st_axes,
                     res["uncertainty"], segs, ident.odr_hz)
    v = _judge(failed, res)
    assert v.verdict == "error" and "no result" in v.reason, v.reason
    # a capable board whose reading is missing altogether (the option on, nothing read) is error too
    v = _judge({"shape": "board-selfcal/1", "applicable": True, "error": "the board's calibrator was not read"}, res)
    assert v.verdict == "error" and "not read" in v.reason
    # the option off: no such check at all
    assert not _named(_judge(None))
    # without G frames the station's own segments stand in for the board's (said so)
    bare = compare(replace(reading, segments=()), st_axes, res["uncertainty"], segs, ident.odr_hz, ident.sensor)
    assert bare.agrees and "standing in" in str(bare.noise["board_estimate_from"])


def test_the_option_belongs_to_thermal_profiles():
    from station.config import ProfileConfig
    from station.profiles import BUILTIN_PROFILES, profile_from_config, with_program_verify

    steps = [s.to_json() for s in BUILTIN_PROFILES["fast-thermal"].steps]
    cfg = ProfileConfig(analysis="thermal", board_selfcal=True,
                        steps=[{k: s[k] for k in ("name", "position", "lamp", "require", "timeout_s")} for s in steps])
    prof = profile_from_config("ft-selfcal", cfg)
    assert prof.board_selfcal and not BUILTIN_PROFILES["fast-thermal"].board_selfcal  # default off
    assert with_program_verify(prof).board_selfcal  # kept when the profile ends with program and verify
    with pytest.raises(ValueError, match="thermal profile's option"):
        profile_from_config("sfem-selfcal", ProfileConfig(analysis="sfem", board_selfcal=True, steps=[
            {"name": "a", "position": "sfem-z0", "require": "static", "dwell_s": 60, "timeout_s": 600}]))
