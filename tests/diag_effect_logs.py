"""Logs with one effect of the library's newer terms injected with a known parameter, for
tests/test_diagnostics_library.py: the plant of tests/diag_plant.py (its own lag and noise code,
independent of station/diagnostics), on a shorter profile.

Plant: the chamber plate ramps 25 -> 60 -> -10 -> 25 C at 3 C/min in +z up, then at 1 C/min in
-z up (two orientations: TDB and TDSF told apart; two rates), 10-minute holds at the turns; the
die follows the plate through a 40 s lag; the temperature sensor reads the die with 0.1 C noise,
quantized to 1 C (a LIS3DSH). 1 Hz, ~4.1 h. Noise: diag_plant.correlated_noise (white 0.7 mg,
bias random walk 4 ug/sqrt(s), flicker 40 ug).

Effects (in mg, added to martinez2022 eq. 1), each written here from its physics:
- bias_rate: + r_i dT_die/dt (C/min of the true die temperature);
- sensor_lag: the sensor reads lag(T_die, tau) (first order); the MEMS sees T_die;
- bias_step: + s_i 1(t > t_step);
- time_drift: + d_i (t - t_mid) in mg/h; time_drift_saturating: + D_i (1 - exp(-(t - t0)/tau)), whose
  initial slope d_i = D_i / tau is the library's d_mg_per_h;
- static_nonlinearity: + n_i Acc0_i^2.
"""

from __future__ import annotations

import numpy as np

from diag_plant import correlated_noise, first_order_lag
from contracts.logfile import DutLog

RATE_HZ = 1.0
ACC0_G = {0: (0.012, -0.008, 1.0), 1: (-0.010, 0.015, -1.0)}
TDB_MG_PER_C = np.array([0.25, -0.18, 0.32])
TDSF_PPM_PER_C = np.array([120.0, -80.0, 150.0])
AMP = np.array([1.0, -0.8, 1.2])  # per-axis pattern of an effect's amplitude

# the default truth of each effect (per-axis values are AMP times the scalar)
TRUTH = {
    "bias_rate": {"r_mg_per_c_per_min": 1.5},
    "sensor_lag": {"tau_s": 180.0},
    "bias_step": {"s_mg": 2.0, "t_step_s": 2.7 * 3600.0},
    "time_drift": {"d_mg_per_h": 0.6},
    "time_drift_saturating": {"d_mg": 2.0, "tau_s": 5400.0},
    "static_nonlinearity": {"n_mg_per_g2": 3.0},
}


def profile(rate_hz: float = RATE_HZ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """time_s, plate temperature C, orientation per sample."""
    temp, pos = [25.0] * int(600 * rate_hz), [0] * int(600 * rate_hz)
    for orient, rate in ((0, 3.0), (1, 1.0)):
        for target, hold in ((60.0, 600.0), (-10.0, 600.0), (25.0, 600.0)):
            cur = temp[-1]
            n_ramp = int(abs(target - cur) / rate * 60.0 * rate_hz)
            temp += list(np.linspace(cur, target, n_ramp + 1)[1:]) + [target] * int(hold * rate_hz)
            pos += [orient] * (n_ramp + int(hold * rate_hz))
    t = np.asarray(temp, float)
    return np.arange(t.size) / rate_hz, t, np.asarray(pos, np.int64)


def make_effect_log(effect: str | None = None, seed: int = 0, **truth) -> tuple[DutLog, dict]:
    """A log with at most one injected effect and its truth ({param: value or per-axis array}).
    The noise depends only on the seed: the same seed without the effect is its control."""
    rng = np.random.default_rng(seed)
    time_s, plate, pos = profile()
    die = first_order_lag(plate, 40.0, RATE_HZ)
    p = {**TRUTH.get(effect, {}), **truth}
    acc0_g = np.array([ACC0_G[int(k)] for k in pos])
    sensor = die
    if effect == "sensor_lag":
        sensor = first_order_lag(die, p["tau_s"], RATE_HZ)
    dt = (die - 25.0)[:, None]
    acc_mg = 1000.0 * acc0_g + dt * (TDB_MG_PER_C + TDSF_PPM_PER_C * acc0_g * 1e-3)
    out: dict = {}
    if effect == "bias_rate":
        out["r_mg_per_c_per_min"] = AMP * p["r_mg_per_c_per_min"]
        acc_mg += (np.gradient(die, time_s) * 60.0)[:, None] * out["r_mg_per_c_per_min"]
    elif effect == "sensor_lag":
        out["tau_s"] = p["tau_s"]
    elif effect == "bias_step":
        out["s_mg"] = AMP * p["s_mg"]
        out["t_step_s"] = p["t_step_s"]
        acc_mg += (time_s > p["t_step_s"])[:, None] * out["s_mg"]
    elif effect == "time_drift":
        out["d_mg_per_h"] = AMP * p["d_mg_per_h"]
        t_mid = 0.5 * (time_s[0] + time_s[-1])
        acc_mg += ((time_s - t_mid) / 3600.0)[:, None] * out["d_mg_per_h"]
    elif effect == "time_drift_saturating":  # library name time_drift, its saturating shape
        out["tau_s"] = p["tau_s"]
        out["d_mg_per_h"] = AMP * p["d_mg"] / (p["tau_s"] / 3600.0)  # the initial slope
        acc_mg += -np.expm1(-(time_s - time_s[0]) / p["tau_s"])[:, None] * AMP * p["d_mg"]
    elif effect == "static_nonlinearity":
        out["n_mg_per_g2"] = AMP * p["n_mg_per_g2"]
        acc_mg += acc0_g**2 * out["n_mg_per_g2"]
    elif effect is not None:
        raise ValueError(f"unknown effect {effect!r}")
    acc_mg += correlated_noise(time_s.size, rng, rate_hz=RATE_HZ)
    temp_meas = np.round(sensor + 0.1 * rng.standard_normal(time_s.size))
    log = DutLog(time_s=time_s, acc_g=acc_mg / 1000.0, temp_c=temp_meas,
                 meta={"serial": f"lib-{effect or 'clean'}-{seed}", "sensor": "LIS3DSH"}, position=pos)
    return log, out
