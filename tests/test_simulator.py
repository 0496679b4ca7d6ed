"""The DUT simulator: determinism, chunking, truth JSON, sensor resolution, hidden effects, the
thermal profiles' shape (checked with the martinez2022 3.3 stability rules) and `station simulate`."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from drivers.sim.physics import HIDDEN_EFFECTS, SENSORS, DutTruth, draw_population, population_from_json
from drivers.sim.profiles import VALIDATION_CYCLES, fast_thermal_steps, run_profile, run_steps, step_table
from drivers.sim.world import EnvConfig, SimWorld
from contracts.logfile import read_log
from contracts.positions import POSITION_INDEX
from contracts.types import StationError


def _world(n=3, seed=11, effects=(), sensor="LIS3DSH"):
    return SimWorld(draw_population(n, seed, sensor=sensor, effects=effects), seed=seed)


# --- determinism and chunking ---------------------------------------------------------------------


def test_same_seed_same_output_other_seed_differs():
    a, b, c = _world(seed=5), _world(seed=5), _world(seed=6)
    for w in (a, b, c):
        w.lamp_on = True
    ca, cb, cc = a.advance(2000), b.advance(2000), c.advance(2000)
    assert np.array_equal(ca.acc_counts, cb.acc_counts)
    assert np.array_equal(ca.temp_counts, cb.temp_counts)
    assert not np.array_equal(ca.acc_counts, cc.acc_counts)


def test_chunking_does_not_change_the_output():
    """advance(1000) == 10 x advance(100), with every effect, the lamp, a turn and a chamber ramp."""

    def drive(w, sizes):
        out = []
        for n in sizes:
            out.append(w.advance(n))
        return out

    worlds = [_world(n=4, seed=3, effects=HIDDEN_EFFECTS) for _ in range(2)]
    for w in worlds:
        w.lamp_on, w.position = True, POSITION_INDEX["N"]
    one = drive(worlds[0], [1000])
    many = drive(worlds[1], [100] * 10)
    for w in worlds:  # second phase: chamber ramp, odd chunk sizes
        w.lamp_on, w.chamber_setpoint_c, w.chamber_ramp_c_per_min = False, 60.0, 1.5
    one += drive(worlds[0], [1500])
    many += drive(worlds[1], [1, 499, 7, 993])

    def cat(chunks, attr):
        return np.concatenate([getattr(c, attr) for c in chunks], axis=-1 if attr == "time_s" else 1)

    for attr in ("acc_counts", "temp_counts", "die_temp_c", "mems_temp_c"):
        assert np.array_equal(cat(one, attr), cat(many, attr)), attr
    assert np.array_equal(np.concatenate([c.time_s for c in one]), np.concatenate([c.time_s for c in many]))
    assert worlds[0].time_s == worlds[1].time_s == pytest.approx(2500 / 3.125)


# --- truth ------------------------------------------------------------------------------------------


def test_truth_json_round_trip_and_forward_model():
    truths = draw_population(5, 42, effects=HIDDEN_EFFECTS)
    doc = json.loads(json.dumps([t.to_json() for t in truths]))
    back = [DutTruth.from_json(d) for d in doc]
    for t, b in zip(truths, back):
        assert json.dumps(t.to_json(), sort_keys=True) == json.dumps(b.to_json(), sort_keys=True)
        assert np.allclose(b.A, b.misalignment @ b.nonorthogonality @ np.diag(b.scale))
        # A maps the raw reading after bias removal back to the true gravity vector
        g = np.array([0.0, 0.6, -0.8])
        assert np.allclose(b.A @ (b.acc0_g(g) - b.bias_g), g)
        assert set(b.effects) == set(HIDDEN_EFFECTS)
    d = truths[0].to_json()
    for key in ("noise_g", "temp_resolution_c", "tdb_mg_per_c", "tdsf_ppm_per_c", "die_tau_s", "self_heat_c"):
        assert key in d


def test_population_spread_like_martinez2022_table6():
    truths = draw_population(64, 0)
    tdb = np.array([t.tdb_mg_per_c for t in truths])
    tdsf = np.array([t.tdsf_ppm_per_c for t in truths])
    assert tdb.min() >= -1.2 and tdb.max() <= 1.4 and tdb.min() < -0.9 and tdb.max() > 1.1
    assert tdsf.max() <= 0.0 and tdsf.min() >= -500.0
    assert (tdsf == 0.0).sum() >= 5 and ((tdsf < 0) & (tdsf > -40)).sum() >= 3
    mis = np.abs(np.array([t.misalignment_deg for t in truths]))
    assert 0.2 < np.median(mis) < 1.0 and mis.max() <= 1.2
    scale_err = np.abs(np.array([t.scale for t in truths]) - 1.0)
    assert 0.01 <= scale_err.min() and scale_err.max() <= 0.04


def test_base_parameters_do_not_depend_on_switched_effects():
    plain = draw_population(3, 9)
    with_fx = draw_population(3, 9, effects=["hysteresis", "bias_t2"])
    for a, b in zip(plain, with_fx):
        da, db = a.to_json(), b.to_json()
        assert db["effects"].keys() == {"bias_t2", "hysteresis"} and da["effects"] == {}
        da.pop("effects"), db.pop("effects")
        assert da == db


def test_unknown_names_are_station_errors():
    with pytest.raises(StationError, match="bogus"):
        draw_population(1, 0, effects=["bogus"])
    with pytest.raises(StationError, match="XYZ"):
        draw_population(1, 0, sensor="XYZ")


# --- sensor resolution ------------------------------------------------------------------------------


def test_lis3dsh_temperature_in_1c_steps_and_acc_in_60ug_steps():
    w = _world(n=2)
    w.lamp_on = True
    c = w.advance(3000)
    ident = w.identity(0)
    temp = ident.temp_c(c.temp_counts[0])
    assert np.array_equal(temp, np.round(temp))  # 1 C steps
    assert len(np.unique(temp)) > 10  # it does follow the heating
    acc = ident.acc_g(c.acc_counts[0])
    assert np.allclose(acc / 60e-6, np.round(acc / 60e-6))
    # the noise floor matches the truth (differences of consecutive samples on a slow ramp)
    noise = np.diff(acc[:, 0]).std() / np.sqrt(2)
    assert noise == pytest.approx(w.duts[0].noise_g, rel=0.15)


def test_adxl355_identity_and_temperature_resolution():
    w = _world(n=1, sensor="ADXL355")
    ident = w.identity(0)
    assert (ident.ug_per_lsb, ident.t_lsb_per_c, ident.t_lsb_at_25c) == (3.9, -9.05, 1885.0)
    c = w.advance(500)
    assert np.all(np.abs(c.temp_counts - 1885) < 60)  # about 25 C
    assert np.all(np.abs(c.acc_counts) < (1 << 19))


# --- thermal behaviour ------------------------------------------------------------------------------


def _stable_segments(time_s, acc, temp, odr=3.125, discard=500, average=1000):
    """martinez2022 3.3: filter 0.05, gradient filter 0.01, log while |grad| < 1 C/min, discard
    500, average 1000; next segment after > 20 C or an orientation change (all axes > 0.8 g)."""
    segs, tf, af, grad, count, start, last = [], temp[0], acc[0].copy(), 10.0, 0, None, None
    for k in range(1, len(time_s)):
        prev = tf
        tf += 0.05 * (temp[k] - tf)
        af += 0.05 * (acc[k] - af)
        grad += 0.01 * ((tf - prev) * odr * 60.0 - grad)
        if last is not None:
            if abs(tf - last[0]) > 20.0 or np.all(np.abs(af - last[1]) > 0.8):
                last, grad, count = None, 10.0, 0
            continue
        if abs(grad) < 1.0:
            count += 1
            if count == discard + 1:
                start = k
            if count == discard + average:
                sl = slice(start, k + 1)
                segs.append((time_s[start], time_s[k], temp[sl].mean(), acc[sl].mean(axis=0)))
                last = (tf, af.copy())
        else:
            count = 0
    return segs


def test_fast_thermal_gives_one_stable_segment_per_phase():
    w = _world(n=3, seed=21)
    logs = run_profile(w, "fast-thermal")
    bounds = np.cumsum([0] + [s.duration_s for s in fast_thermal_steps()])
    assert 60 * 60 <= bounds[-1] <= 95 * 60
    for log in logs:
        segs = _stable_segments(log.time_s, log.acc_g, log.temp_c)
        assert len(segs) == 4, (log.serial, segs)
        for k, (t0, t1, _, _) in enumerate(segs):  # one in each phase
            assert bounds[k] <= t0 < t1 <= bounds[k + 1], (log.serial, k, t0, t1)
        temps = [s[2] for s in segs]
        assert temps[1] - temps[0] > 20 and temps[2] - temps[3] > 20, temps
        assert np.all(segs[0][3] > 0.4) and np.all(segs[2][3] < -0.4)  # P then N
        assert temps[2] > temps[1]  # hotter over the lamp after the turn


def test_plate_hotter_over_the_lamp_after_the_turn_and_self_heating_visible():
    w = _world(n=2, seed=4)
    cols = run_steps(w, fast_thermal_steps())
    t, plate = cols["time_s"], cols["plate_temp_c"]
    env = EnvConfig()
    end_p_hot = plate[np.searchsorted(t, (14 + 25) * 60) - 1]
    end_n_hot = plate[np.searchsorted(t, (14 + 45) * 60) - 1]
    assert end_p_hot - env.ambient_c > 25  # lamp: > 20 C above ambient
    assert end_n_hot - end_p_hot > 3  # turned over the lamp: hotter (martinez2022 Fig. 8)
    # self-heating: the die (temperature sensor) ends the ambient phase above the plate
    temp = w.identity(0).temp_c(cols["temp_counts"][0])
    k = np.searchsorted(t, 14 * 60)
    assert temp[k - 300 : k].mean() - plate[k - 1] > 1.5
    assert temp[:10].mean() < temp[k - 300 : k].mean() - 1.5


def test_chamber_holds_settle_to_the_set_point():
    w = _world(n=2, seed=8)
    w.chamber_setpoint_c, w.chamber_ramp_c_per_min = -10.0, 2.0
    c = w.advance(int((17.5 + 15) * 60 * 3.125))
    assert c.chamber_air_c[int(17.5 * 60 * 3.125)] == pytest.approx(-10.0)
    self_heat = np.array([d.self_heat_c for d in w.duts])
    assert np.all(np.abs(c.die_temp_c[:, -1] - self_heat - (-10.0)) < 0.3)  # die = plate + self-heating
    assert abs(w.identity(0).temp_c(c.temp_counts[0, -300:]).mean() - self_heat[0] + 10.0) < 0.5
    assert abs(w.plate_temp_c + 10.0) < 0.3


def test_uncalibrated_24_position_rmse_like_sensors2023():
    w = _world(n=8, seed=2)
    logs = run_profile(w, "sfem-24")
    rmse = []
    for log in logs:
        means = []
        for s in step_table("sfem-24"):
            if s["chamber_setpoint_c"] == 25.0 and not s["label"].startswith("settle"):
                m = (log.time_s >= s["t_start_s"] + 20) & (log.time_s < s["t_end_s"])
                means.append(log.acc_g[m].mean(axis=0))
                assert np.allclose(np.linalg.norm(log.ref_dir[m], axis=1), 1.0)
        assert len(means) == 24
        rmse.append(np.sqrt(np.mean((np.linalg.norm(means, axis=1) - 1.0) ** 2)) * 1e3)
    assert 20 < np.mean(rmse) < 80, rmse


# --- hidden effects ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def validation_base():
    return run_profile(SimWorld(draw_population(2, 5), seed=5), "validation")


@pytest.mark.parametrize("effect", HIDDEN_EFFECTS)
def test_each_hidden_effect_changes_the_acceleration_only(effect, validation_base):
    logs = run_profile(SimWorld(draw_population(2, 5, effects=[effect]), seed=5), "validation")
    d_mg = np.array([(a.acc_g - b.acc_g) for a, b in zip(logs, validation_base)]) * 1e3
    assert np.abs(d_mg).max() > 2.5, effect  # well above one 0.06 mg LSB and the 0.5 mg noise
    for a, b in zip(logs, validation_base):
        assert np.array_equal(a.temp_c, b.temp_c)  # no effect is seen by the temperature sensor
        assert a.meta["effects"] == effect and b.meta["effects"] == "none"


def test_validation_profile_cycles_have_their_own_position_and_ramp_rate(validation_base):
    log = validation_base[0]
    assert log.meta["profile"] == "validation"
    positions = list(dict.fromkeys(log.position.tolist()))
    assert positions == [POSITION_INDEX["P"]] + [POSITION_INDEX[p] for p, _ in VALIDATION_CYCLES][1:]
    rates = []
    for name, rate in VALIDATION_CYCLES:
        m = log.position == POSITION_INDEX[name]
        t, temp = log.time_s[m], log.temp_c[m]
        assert temp.max() > 55 and temp.min() < -5
        up = (temp > 0) & (temp < 50)
        # the steepest stretch of the temperature in this cycle, in C/min, from a 20 min window
        w = int(20 * 60 * 3.125)
        slopes = np.abs(temp[w:] - temp[:-w]) / 20.0
        rates.append(slopes[up[w:]].max())
    assert rates[VALIDATION_CYCLES.index(("+x", 0.5))] < 0.7
    assert rates[VALIDATION_CYCLES.index(("P", 2.0))] > 1.6


# --- command line ------------------------------------------------------------------------------------


def _station(*args):
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True, timeout=120)


def test_cli_writes_logs_and_truth(tmp_path):
    out = _station("simulate", "--out", str(tmp_path), "--duts", "3", "--seed", "7", "--effect", "bias_t2", "--effect", "hysteresis")
    assert out.returncode == 0, out.stderr
    truth = json.loads((tmp_path / "truth.json").read_text())
    duts = population_from_json(truth)
    assert [d.serial for d in duts] == ["SIM0001", "SIM0002", "SIM0003"]
    assert truth["effects"] == ["bias_t2", "hysteresis"] and truth["profile"] == "fast-thermal" and truth["seed"] == 7
    same = draw_population(3, 7, effects=["bias_t2", "hysteresis"])
    assert [d.to_json() for d in duts] == json.loads(json.dumps([d.to_json() for d in same]))
    for d in duts:
        log = read_log(tmp_path / f"{d.serial}.csv")
        assert log.meta["serial"] == d.serial and log.meta["sensor"] == "LIS3DSH" and log.meta["seed"] == "7"
        assert log.lamp is not None and log.position is not None and log.ref_dir is not None
        assert set(np.unique(log.lamp)) == {0, 1} and set(np.unique(log.position)) == {0, 1}
        assert len(log) == int(round(92 * 60 * 3.125))
    assert SENSORS["LIS3DSH"].odr_hz == truth["odr_hz"]


@pytest.mark.parametrize(
    "args, word",
    [
        (["--effect", "warp_drive"], "warp_drive"),
        (["--profile", "ten-position"], "ten-position"),
        (["--sensor", "MPU6050"], "MPU6050"),
        (["--duts", "0"], "--duts"),
    ],
)
def test_cli_rejects_bad_input_in_one_line(tmp_path, capsys, args, word):
    from cli.main import main

    assert main(["simulate", "--out", str(tmp_path / "o"), *args]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and word in lines[0] and "Traceback" not in err
    assert not (tmp_path / "o" / "truth.json").exists()


def test_power_cycle_restarts_the_warm_up_transient():
    w = _world(n=2, seed=13, effects=["self_heating"])
    w.advance(3000)
    before = w.advance(10)
    die_before = w.die_temp_c.copy()
    w.power_cycle(0)
    after = w.advance(10)
    w_mg = np.asarray(w.duts[0].effects["self_heating"]["w_mg"])
    jump_mg = (after.acc_counts[0].mean(0) - before.acc_counts[0].mean(0)) * 0.06
    assert np.allclose(jump_mg, w_mg * (1 - np.exp(-3010 / 3.125 / w.duts[0].effects["self_heating"]["tau_s"])), atol=0.6)
    assert np.allclose(after.acc_counts[1].mean(0), before.acc_counts[1].mean(0), atol=20)  # board 1 untouched
    assert abs(after.die_temp_c[0, 0] - die_before[0]) < 0.05  # a quick reset keeps the die warm
    w.power_cycle(1, off_s=float("inf"))  # cold start: the die's self-heating starts over
    assert w.advance(1).die_temp_c[1, 0] < die_before[1] - 1.5
