"""The effect library's newer terms (issue 38): bias_rate, sensor_lag, bias_step, time_drift (linear
and saturating), static_nonlinearity, and the physical bound of self_heating.

Each effect is injected with a known parameter into a log of tests/diag_effect_logs.py (its own
plant and noise code: chamber ramps at 3 and 1 C/min in two orientations, 1 C-quantized sensor, a
LIS3DSH-class wandering bias, 1 Hz, ~4.3 h), and `diagnose(logs, add=[name])` must recover the
parameter (within a few of its reported sigmas, or a tolerance a few times the error measured over
seeds 0-5) and bring the held-out error down to near the control log's (same seed and noise, no
effect). Ranking and admission are not asserted here (the gate has tests of its own); the
candidates are limited to the effect itself, which keeps the file at a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from diag_effect_logs import make_effect_log
from station.diagnostics.effects import BUILTIN_NAMES, get_effect, lag_filter, temperature_rate
from station.diagnostics.ranking import diagnose

SEED = 1
NEW = ("bias_rate", "sensor_lag", "bias_step", "time_drift", "static_nonlinearity")
# the held-out error with the effect added, against the control log's baseline: measured over seeds
# 0-5 at most 1.40x for bias_rate (the library's dT/dt is smoothed over +-2 min, the plant's die rate
# turns within its 40 s lag: a residual at each of the 12 ramp corners), 1.35x for a saturating
# time_drift (4.3 h pin its tau loosely), <= 1.13x for the others
NEAR_FLOOR = 1.5


@pytest.fixture(scope="module")
def control_heldout_mg() -> float:
    log, _ = make_effect_log(None, seed=SEED)
    return diagnose([log], candidates=[]).to_json()["baseline"]["heldout_rms_mg"]


@pytest.fixture(scope="module")
def diagnosed():
    cache: dict = {}

    def get(name: str):
        if name not in cache:
            log, truth = make_effect_log(name, seed=SEED)
            doc = diagnose([log], add=[name], candidates=[name]).to_json()
            cache[name] = (doc, truth, doc["model"]["parameters"][log.meta["serial"]]["effects"].get(name, {}))
        return cache[name]

    return get


def _heldout_falls(doc: dict, control_mg: float, factor: float = 0.6):
    base, step = doc["baseline"]["heldout_rms_mg"], doc["staircase"][-1]
    assert step["effects"] == doc["model"]["effects"] and step["effects"][-1] in NEW, step["effects"]
    assert step["heldout_rms_mg"] < factor * base, (step["heldout_rms_mg"], base)
    assert step["heldout_rms_mg"] <= NEAR_FLOOR * control_mg, (step["heldout_rms_mg"], control_mg)


def _per_axis_close(fitted: dict, truth: np.ndarray, n_sigma: float, abs_tol: float = 0.0):
    for i, ax in enumerate("xyz"):
        v, s = fitted[ax]["value"], fitted[ax]["sigma"]
        assert s is not None and s > 0, (ax, fitted[ax])
        assert abs(v - truth[i]) <= n_sigma * s + abs_tol, (ax, v, s, truth[i])


def test_the_new_effects_are_in_the_library_and_documented():
    for name in NEW:
        assert name in BUILTIN_NAMES
        e = get_effect(name)
        assert e.note and e.needs and e.identify_hint, name
        for p in e.linear:
            assert "_mg" in p or "_ppm" in p, (name, p)  # the unit is in the name
    # a sensor's offset and gain are eq. 1's; its leading the MEMS is thermal_lag
    note = get_effect("sensor_lag").note
    assert "offset" in note and "gain" in note and "thermal_lag" in note
    assert get_effect("static_nonlinearity").identify_hint


def test_self_heating_time_constant_is_a_board_warm_up():
    (tau,) = get_effect("self_heating").nonlinear
    assert (tau.lower, tau.upper) == (10.0, 3600.0)


def test_bias_rate_recovered(diagnosed, control_heldout_mg):
    doc, truth, fit = diagnosed("bias_rate")
    # measured |error| <= 0.05 mg per C/min, sigma ~0.05-0.07
    _per_axis_close(fit["r_mg_per_c_per_min"], truth["r_mg_per_c_per_min"], n_sigma=4.0)
    _heldout_falls(doc, control_heldout_mg, factor=0.2)


def test_sensor_lag_time_constant_recovered(diagnosed, control_heldout_mg):
    doc, truth, fit = diagnosed("sensor_lag")
    tau = fit["tau_s"]
    # measured over seeds: 175-184 s for 180 s, sigma 3-4 s
    assert abs(tau["value"] - truth["tau_s"]) <= 4.0 * tau["sigma"], (tau, truth)
    assert abs(tau["value"] - truth["tau_s"]) <= 0.05 * truth["tau_s"], (tau, truth)
    assert f"tau {tau['value']:.3g} s" in doc["staircase"][-1]["shape"]
    _heldout_falls(doc, control_heldout_mg, factor=0.3)


def test_sensor_lag_hook_inverts_a_first_order_lag():
    """T_die = T_meas + tau dT_meas/dt undoes a first-order lag away from the ramp corners, also on
    a 1 C-quantized sensor (the rate is smoothed)."""
    t = np.arange(0.0, 7200.0, 1.0)
    die = 25.0 + np.clip((t - 600.0) / 60.0, 0.0, 40.0)  # 1 C/min from 10 min, holds at 65 C
    meas = np.round(lag_filter(die, t, 200.0))
    seen = get_effect("sensor_lag").temperature(meas, t, {"tau_s": 200.0})
    ramp = (t > 600 + 5 * 200) & (t < 600 + 2400 - 300)
    hold = t > 600 + 2400 + 6 * 200
    assert np.max(np.abs(seen[ramp] - die[ramp])) < 0.6  # meas lags by 3.3 C here
    assert np.max(np.abs(seen[hold] - die[hold])) < 0.6
    assert np.max(np.abs(temperature_rate(meas, t)[hold])) < 2e-3  # no rate from the quantization


def test_bias_step_time_and_size_recovered(diagnosed, control_heldout_mg):
    doc, truth, fit = diagnosed("bias_step")
    t_fit_s = fit["t_step_h"]["value"] * 3600.0
    pct = fit["t_step_pct"]
    span_s = t_fit_s / (pct["value"] / 100.0)  # the log starts at t = 0
    # measured within 1 s of the truth over seeds 0-5; sigma of the place ~3-4 s
    assert abs(t_fit_s - truth["t_step_s"]) <= 10.0, (t_fit_s, truth)  # within one 10 s block
    assert abs(t_fit_s - truth["t_step_s"]) <= 5.0 * pct["sigma"] / 100.0 * span_s + 2.0
    assert doc["staircase"][-1]["shape"].startswith("step at t = 2.7 h"), doc["staircase"][-1]["shape"]
    # the bias random walk (4 ug/sqrt(s)) moves the levels on either side of the step by ~0.2 mg,
    # which no fit can tell from the step (measured |error| <= 0.32 mg, sigma ~0.08)
    _per_axis_close(fit["s_mg"], truth["s_mg"], n_sigma=3.0, abs_tol=0.4)
    _heldout_falls(doc, control_heldout_mg, factor=0.5)


def test_time_drift_recovered(diagnosed, control_heldout_mg):
    doc, truth, fit = diagnosed("time_drift")
    # measured |error| <= 1.6 sigma over seeds 0-5 (sigma ~0.1-0.2 mg/h for 0.5-0.7 mg/h), whether
    # the family kept the line or (3 of 6 seeds: the random walk bends it) a saturating shape with
    # tau far beyond the log, d then its initial slope
    _per_axis_close(fit["d_mg_per_h"], truth["d_mg_per_h"], n_sigma=3.0)
    shape = doc["staircase"][-1]["shape"]
    if shape != "linear in time":
        assert shape.startswith("saturating") and fit["tau_s"]["value"] > 2 * 4.3 * 3600, (shape, fit["tau_s"])
    _heldout_falls(doc, control_heldout_mg, factor=0.7)


def test_time_drift_saturating_shape_recovered(control_heldout_mg):
    """Humidity uptake: + D (1 - exp(-t/tau)), D = 2 mg, tau 1.5 h; the family chooses the saturating
    shape, its tau and initial slope D/tau."""
    log, truth = make_effect_log("time_drift_saturating", seed=SEED)
    doc = diagnose([log], add=["time_drift"], candidates=["time_drift"]).to_json()
    fit = doc["model"]["parameters"][log.meta["serial"]]["effects"]["time_drift"]
    assert doc["staircase"][-1]["shape"].startswith("saturating"), doc["staircase"][-1]["shape"]
    tau = fit["tau_s"]
    # measured over seeds 0-5: tau 3850-8900 s for 5400 s, at most 3.1 sigma (sigma 540-1130 s);
    # the initial slope within 2.8 sigma (sigma 0.24-0.55 mg/h for 1.1-1.6 mg/h)
    assert abs(tau["value"] - truth["tau_s"]) <= 4.0 * tau["sigma"], (tau, truth["tau_s"])
    _per_axis_close(fit["d_mg_per_h"], truth["d_mg_per_h"], n_sigma=4.0)
    _heldout_falls(doc, control_heldout_mg, factor=0.85)  # measured <= 0.76 of the baseline's


def test_static_nonlinearity_is_reported_not_identifiable(diagnosed, control_heldout_mg):
    """A free Acc0 per orientation absorbs n Acc0^2: the identifiability check says so, with the data
    that would identify it, and the added step carries the warning (its numbers are not trusted)."""
    doc, _, _ = diagnosed("static_nonlinearity")
    unident = {u["effect"]: u for u in doc["unidentifiable"]}
    assert "static_nonlinearity" in unident
    hint = unident["static_nonlinearity"]["test_to_identify"]
    assert "known" in hint and ("dividing head" in hint or "centrifuge" in hint)
    assert "static_nonlinearity" not in {r["effect"] for r in doc["ranking"]}
    step = doc["staircase"][-1]
    assert step["model"] == "+static_nonlinearity" and "not identifiable" in step["warning"]
    # the injected term is a constant per orientation: the baseline alone is already at the floor
    assert doc["baseline"]["heldout_rms_mg"] <= 1.02 * control_heldout_mg
