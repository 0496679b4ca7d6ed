"""The independent plant of tests/diag_plant2.py checked against closed forms (its own physics,
before any diagnosis is benchmarked on it): the lag filter on a ramp, the temperature sensor's lag,
the step, the hysteresis operators, the noise's Allan deviation term by term, the schedule and the
plate moves, and the control twin (same DUT and noise: log - control is exactly the effect)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import diag_plant2 as G
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX

RATE = G.FAST_RATE_HZ


@pytest.fixture(scope="module")
def control():
    return G.make_log((), seed=5, rate_hz=RATE)


def _pair(effect: str, seed: int = 5):
    log, truth = G.make_log([effect], seed=seed, rate_hz=RATE)
    ctrl, _ = G.make_log((), seed=seed, rate_hz=RATE)
    return log, truth, ctrl, (log.acc_g - ctrl.acc_g) * 1000.0


def _settled_ramps(time_s: np.ndarray, settle_s: float = 900.0) -> np.ndarray:
    """Samples on a chamber ramp at least settle_s after it started (every lag has settled)."""
    m = np.zeros(time_s.size, bool)
    for s in G.schedule():
        if s["kind"] == "ramp" and s["t1"] - s["t0"] > settle_s + 60.0:
            m |= (time_s >= s["t0"] + settle_s) & (time_s < s["t1"])
    return m


def test_lag1_exact_on_a_ramp():
    # y' = (x - y)/tau, x = m t, y(0) = 0: y = m (t - tau (1 - exp(-t/tau)))
    t = np.arange(5000) / 3.125
    m, tau = 0.05, 120.0
    y = G.lag1(m * t, tau, 3.125)
    assert np.max(np.abs(y - m * (t - tau * (1.0 - np.exp(-t / tau))))) < 1e-9


def test_schedule_six_orientations_rates_and_length():
    segs = G.schedule()
    ramps = [s for s in segs if s["kind"] == "ramp"]
    rates = {round(abs(s["c1"] - s["c0"]) / (s["t1"] - s["t0"]) * 60.0, 6) for s in ramps}
    assert len(rates) >= 2
    assert {s["position"] for s in ramps} == {"+z", "-z", "+x", "-x", "+y", "-y"}
    assert min(s["c1"] for s in ramps) == -10.0 and max(s["c1"] for s in ramps) == 60.0
    pl = G.plant(G.RATE_HZ)
    assert 110_000 <= pl["time_s"].size <= 125_000  # ~10 h at 3.125 Hz
    short = G.schedule(hours=4.0)
    assert abs(short[-1]["t1"] - 4 * 3600.0) < 1.0


def test_moves_only_between_orientations_and_in_between(control):
    log, truth = control
    pos = log.position
    moving = pos == -1
    edges = np.flatnonzero(np.diff(moving.astype(int)))
    starts, ends = edges[::2] + 1, edges[1::2] + 1  # [start, end) of each run of -1
    assert len(starts) == len(G.CYCLES) - 1 == len(ends)
    order = [pos[0]]
    for a, b in zip(starts, ends):
        assert abs((b - a) / RATE - G.MOVE_S) <= 1.0 / RATE + 1e-9
        before, after = pos[a - 1], pos[b]
        assert before >= 0 and after >= 0 and before != after
        order.append(after)
        # the gravity vector turns from one orientation to the next, monotonically, unit length
        g = truth["arrays"]["gravity"][a:b]
        ga, gb = GRAVITY_DIRECTIONS[before], GRAVITY_DIRECTIONS[after]
        assert np.allclose(np.linalg.norm(g, axis=1), 1.0)
        ang = np.arccos(np.clip(g @ ga, -1.0, 1.0))
        assert np.all(np.diff(ang) > 0) and 0 < ang[0] and ang[-1] < math.acos(float(np.clip(ga @ gb, -1, 1)))
        # and the logged acceleration is in between: neither orientation's reading
        mid = (a + b) // 2
        assert np.linalg.norm(log.acc_g[mid] - log.acc_g[a - 1]) > 0.3
        assert np.linalg.norm(log.acc_g[mid] - log.acc_g[b]) > 0.3
    assert order == [POSITION_INDEX[p] for p, _ in G.CYCLES]
    # each run at a position holds that position's gravity vector
    at = ~moving
    assert np.allclose(truth["arrays"]["gravity"][at], GRAVITY_DIRECTIONS[pos[at]])


def test_temperature_sensor_quantised_and_tracks_the_die(control):
    log, truth = control
    assert np.all(log.temp_c == np.round(log.temp_c))
    err = log.temp_c - truth["arrays"]["die_c"]
    assert np.max(np.abs(err)) <= 2.0
    assert abs(np.mean(err)) < 0.05


@pytest.mark.parametrize("effect,key", [("sensor_lag", "sensor_c"), ("thermal_lag", "mems_c")])
def test_lag_on_ramps_is_tau(effect, key):
    log, truth, _, diff = _pair(effect)
    tau = truth["effects"][effect]["tau_s"]
    die = truth["arrays"]["die_c"]
    m = _settled_ramps(log.time_s)
    rate_s = np.gradient(die, log.time_s)
    lagged = truth["arrays"][key]
    # on a ramp a first-order lag is the input tau seconds ago: (die - lagged) / rate = tau
    assert np.sum((die - lagged)[m] * rate_s[m]) / np.sum(rate_s[m] ** 2) == pytest.approx(tau, rel=0.01)
    if effect == "sensor_lag":
        # the logged (noisy, 1 C) temperature lags the die by tau too; the MEMS sees the die
        est = np.sum((die - log.temp_c)[m] * rate_s[m]) / np.sum(rate_s[m] ** 2)
        assert est == pytest.approx(tau, rel=0.05)
        assert np.all(diff == 0.0)
    else:
        dut = truth["dut"]
        acc0 = np.asarray(dut["bias_g"]) + truth["arrays"]["gravity"] @ np.asarray(dut["A"]).T
        drift = np.asarray(dut["tdb_mg_per_c"]) + 1e-3 * np.asarray(dut["tdsf_ppm_per_c"]) * acc0
        assert np.allclose(diff, (lagged - die)[:, None] * drift, atol=1e-6)


def test_bias_step_at_the_stated_time():
    log, truth, _, diff = _pair("bias_step")
    p = truth["effects"]["bias_step"]
    t_step, s = p["t_step_s"], np.asarray(p["s_mg"])
    t_end = log.time_s[-1]
    assert 0.35 * t_end < t_step < 0.65 * t_end
    assert log.position[np.searchsorted(log.time_s, t_step)] >= 0
    assert np.all(1.0 <= np.abs(s)) and np.all(np.abs(s) <= 2.0)
    before = log.time_s < t_step
    assert np.max(np.abs(diff[before])) < 1e-6
    assert np.allclose(diff[~before], s, atol=1e-6)


def test_control_twin_is_the_same_dut_and_noise():
    for effect, closed in [
        ("bias_t2", lambda tr, dT: dT[:, None] ** 2 * np.asarray(tr["effects"]["bias_t2"]["c2_mg_per_c2"])),
        ("self_heating", lambda tr, dT: np.exp(-tr["t"] / 1200.0)[:, None] * np.asarray(tr["effects"]["self_heating"]["w_mg"])),
        ("time_drift", lambda tr, dT: (1.0 - np.exp(-tr["t"] / tr["effects"]["time_drift"]["tau_s"]))[:, None]
         * np.asarray(tr["effects"]["time_drift"]["d_mg"])),
    ]:
        log, truth, ctrl, diff = _pair(effect)
        assert np.array_equal(log.temp_c, ctrl.temp_c) and np.array_equal(log.position, ctrl.position)
        truth["t"] = log.time_s
        assert np.allclose(diff, closed(truth, truth["arrays"]["die_c"] - 25.0), atol=1e-6), effect


def test_static_nonlinearity_is_constant_per_orientation():
    log, _, _, diff = _pair("static_nonlinearity")
    levels = []
    for p in np.unique(log.position[log.position >= 0]):
        d = diff[log.position == p]
        assert np.ptp(d, axis=0).max() < 1e-6
        levels.append(d[0])
    assert np.ptp(np.array(levels), axis=0).min() > 1.0  # mg: +-1 g on an axis vs 0 g


def test_hysteresis_operators_closed_form():
    # a triangle 25 -> 45 -> 5 -> 45: the relay switches exactly width_c after each reversal
    T = np.concatenate([np.linspace(25, 45, 201), np.linspace(45, 5, 401)[1:], np.linspace(5, 45, 401)[1:]])
    z = G.relay(T, 4.0)
    assert z[0] == -1 and z[T.argmax() - 1] == 1
    k_down = np.flatnonzero(np.diff(z) < 0)
    k_up = np.flatnonzero(np.diff(z) > 0)
    assert T[k_down[0] + 1] == pytest.approx(45 - 4.0, abs=0.11)
    assert T[k_up[-1] + 1] == pytest.approx(5 + 4.0, abs=0.11)
    b = G.backlash(T, 8.0)
    assert b.min() == pytest.approx(-1.0) and b.max() == pytest.approx(1.0)
    i = 200 + 20  # 2 C after the top: the play moves linearly, slope 2/width
    assert b[i] == pytest.approx(1.0 - 2.0 * 2.0 / 8.0)


def test_hvac_period_and_popcorn_levels():
    log, truth, _, diff = _pair("hvac")
    f = np.fft.rfftfreq(diff.shape[0], 1.0 / RATE)
    spec = np.abs(np.fft.rfft(diff[:, 0] - diff[:, 0].mean()))
    assert 1.0 / f[np.argmax(spec[1:]) + 1] == pytest.approx(2400.0, rel=0.03)
    log, truth, _, diff = _pair("popcorn")
    a = np.asarray(truth["effects"]["popcorn"]["a_mg"])
    on = np.abs(diff[:, 0] - a[0]) < 1e-6
    assert np.all(on | (np.abs(diff[:, 0]) < 1e-6)) and 0 < on.mean() < 0.5
    assert np.allclose(diff[on], a, atol=1e-6)
    inside = np.zeros(on.size, bool)
    for t0, t1 in truth["effects"]["popcorn"]["bursts_s"]:
        inside |= (log.time_s >= t0) & (log.time_s < t1)
    assert not np.any(on & ~inside)


def _expected_avar(m: int, dt: float, white: float, rw: float, flicker: float, taus) -> float:
    """Allan variance at m samples of the generator's discrete noise, term by term (exact)."""
    v = white**2 / m  # white
    q = rw**2 * dt  # random walk: increments of variance q per sample
    v += q * (2.0 * m * m + 1.0) / (6.0 * m)
    k = np.arange(-(m - 1), m)
    w = (m - np.abs(k)).astype(float)
    for tau in taus:  # Gauss-Markov: R(k) = s^2 a^|k|; AVAR = Var(mean) - Cov(consecutive means)
        a, s2 = math.exp(-dt / tau), flicker**2 / len(taus)
        v += s2 * (np.sum(w * a ** np.abs(k)) - np.sum(w * a ** (m + k))) / (m * m)
    return v


def test_noise_allan_deviation_matches_its_terms():
    rate, n = 1.0, 1_500_000
    x = G.accel_noise(n, rate, np.random.default_rng(11))
    for m, tol in ((1, 0.02), (10, 0.03), (100, 0.05), (1000, 0.08), (4000, 0.12)):
        got = math.sqrt(np.mean([G.allan_deviation(x[:, i], rate, m) ** 2 for i in range(3)]))
        want = math.sqrt(_expected_avar(m, 1.0 / rate, G.WHITE_MG, G.RW_MG_PER_SQRT_S, G.FLICKER_MG, G.FLICKER_TAU_S))
        assert got == pytest.approx(want, rel=tol), (m, got, want)
    # the random walk dominates at long averaging times: ADEV ~ K sqrt(tau / 3)
    assert _expected_avar(4000, 1.0, G.WHITE_MG, G.RW_MG_PER_SQRT_S, G.FLICKER_MG, G.FLICKER_TAU_S) == pytest.approx(
        G.RW_MG_PER_SQRT_S**2 * 4000 / 3, rel=0.1)
    # noise_scale multiplies every term
    y = G.accel_noise(1000, rate, np.random.default_rng(3), scale=2.0)
    assert np.allclose(y, 2.0 * G.accel_noise(1000, rate, np.random.default_rng(3)))


def test_dut_population_ranges():
    tdb = np.array([G.draw_dut(s)["tdb_mg_per_c"] for s in range(40)])
    tdsf = np.array([G.draw_dut(s)["tdsf_ppm_per_c"] for s in range(40)])
    assert tdb.min() >= -1.2 and tdb.max() <= 1.4 and tdsf.min() >= -500 and tdsf.max() <= 0
    assert np.ptp(tdb) > 1.5 and np.ptp(tdsf) > 300


def test_every_effect_makes_a_log():
    for e in G.EFFECTS:
        log, truth = G.make_log([e], seed=1, rate_hz=RATE, hours=2.0, keep_arrays=False)
        assert e in truth["effects"] and np.all(np.isfinite(log.acc_g)) and len(log) == truth["n"]
    with pytest.raises(ValueError):
        G.make_log(["nope"])
