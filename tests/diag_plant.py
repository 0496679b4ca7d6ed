"""An accelerometer log generator written for the diagnostics tests, independent of drivers/sim and of
station/diagnostics/effects.py: its own thermal plant, its own hysteresis and lag physics, its own
correlated noise. A diagnosis that only knew the project's simulator would be caught here.

Plant: a chamber plate ramps between -10 and 60 C at 3 C/min and at 1 C/min (two rates tell a lag
from a hysteresis) with 10-minute holds at the turns, in two orientations (+1 g and -1 g on z, so
TDB and TDSF are told apart); the die follows the plate through a 40 s lag; the temperature sensor
reads the die with 0.1 C noise, quantized to 1 C (as the LIS3DSH's). Sample rate 1 Hz, ~8.5 h.

Noise (a LIS3DSH-class part, per axis): white 0.7 mg per sample, bias random walk 4 ug/sqrt(s),
flicker 40 ug (three Gauss-Markov processes, 60/600/6000 s): the residual of a perfect model is
not white, as on a real sensor.

Effects (terms added to martinez2022 eq. 1, in mg), each with its own code here:
- hysteresis of three shapes on the die temperature: relay (switch after a reversal of `width_c`),
  backlash (play of total travel `width_c`: linear, then saturated), smooth (exponential approach);
  and a mixture of two mechanisms (a 3 C backlash and a 20 C smooth approach);
- thermal lag: the MEMS sees the die through a first-order lag, or through two in series (die and
  package), in the drift term dT (TDB + TDSF Acc0);
- bias polynomials: + c2 dT^2, + c3 dT^3.
"""

from __future__ import annotations

import math

import numpy as np

from contracts.logfile import DutLog

RATE_HZ = 1.0
T_LO_C, T_HI_C = -10.0, 60.0


def _setpoints() -> list[tuple[int, float, float, float]]:
    """(orientation, target C, ramp C/min, hold s at the target)."""
    out = []
    for orient, rates in ((0, (3.0, 1.0)), (1, (1.0, 3.0))):
        for rate in rates:
            out += [(orient, T_HI_C, rate, 600.0), (orient, T_LO_C, rate, 600.0), (orient, 25.0, rate, 300.0)]
    return out


def plate_profile(rate_hz: float = RATE_HZ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """time_s, plate temperature C, orientation (0: +z up, 1: -z up) per sample."""
    t_c, pos = [25.0] * int(600 * rate_hz), [0] * int(600 * rate_hz)
    for orient, target, rate, hold in _setpoints():
        cur = t_c[-1]
        n_ramp = int(abs(target - cur) / rate * 60.0 * rate_hz)
        t_c += list(np.linspace(cur, target, n_ramp + 1)[1:])
        t_c += [target] * int(hold * rate_hz)
        pos += [orient] * (n_ramp + int(hold * rate_hz))
    temp = np.asarray(t_c, float)
    return np.arange(temp.size) / rate_hz, temp, np.asarray(pos, np.int64)


def first_order_lag(x: np.ndarray, tau_s: float, rate_hz: float = RATE_HZ) -> np.ndarray:
    a = math.exp(-1.0 / (rate_hz * tau_s))
    y = np.empty_like(x)
    acc = x[0]
    for k, v in enumerate(x):
        acc = a * acc + (1.0 - a) * v
        y[k] = acc
    return y


def relay(temp: np.ndarray, threshold_c: float) -> np.ndarray:
    z, hi, lo = 0.0, temp[0], temp[0]
    out = np.empty_like(temp)
    for k, v in enumerate(temp):
        hi, lo = max(hi, v), min(lo, v)
        if z >= 0 and v < hi - threshold_c:
            z, lo = -1.0, v
        elif z <= 0 and v > lo + threshold_c:
            z, hi = 1.0, v
        out[k] = z
    return out


def backlash(temp: np.ndarray, travel_c: float) -> np.ndarray:
    r = travel_c / 2.0
    y = temp[0]
    out = np.empty_like(temp)
    for k, v in enumerate(temp):
        y = min(max(y, v - r), v + r)
        out[k] = (v - y) / r
    return out


def smooth(temp: np.ndarray, width_c: float) -> np.ndarray:
    z = 0.0
    out = np.empty_like(temp)
    out[0] = 0.0
    for k in range(1, temp.size):
        d = temp[k] - temp[k - 1]
        if d:
            s = 1.0 if d > 0 else -1.0
            z = s + (z - s) * math.exp(-abs(d) / width_c)
        out[k] = z
    return out


def correlated_noise(n: int, rng: np.random.Generator, white_mg: float = 0.7, rw_mg_per_sqrt_s: float = 0.004,
                     flicker_mg: float = 0.04, rate_hz: float = RATE_HZ) -> np.ndarray:
    dt = 1.0 / rate_hz
    out = white_mg * rng.standard_normal((n, 3))
    out += np.cumsum(rw_mg_per_sqrt_s * math.sqrt(dt) * rng.standard_normal((n, 3)), axis=0)
    for tau in (60.0, 600.0, 6000.0):
        a = math.exp(-dt / tau)
        sig = flicker_mg / math.sqrt(3.0)
        e = sig * math.sqrt(1 - a * a) * rng.standard_normal((n, 3))
        x = np.empty((n, 3))
        acc = sig * rng.standard_normal(3)
        for k in range(n):  # Gauss-Markov: stationary from the first sample
            acc = a * acc + e[k]
            x[k] = acc
        out += x
    return out


def make_log(effect: str | None = None, seed: int = 0, **p) -> DutLog:
    """A log with at most one effect: "relay", "backlash", "smooth", "mixture", "lag1", "lag2",
    "bias2", "bias3".

    The noise depends only on the seed, so the same seed without the effect is its control."""
    rng = np.random.default_rng(seed)
    time_s, plate, pos = plate_profile()
    die = first_order_lag(plate, 40.0)
    mems = die
    if effect == "lag1":
        mems = first_order_lag(die, p.get("tau_s", 150.0))
    elif effect == "lag2":
        mems = first_order_lag(first_order_lag(die, p.get("tau_s", 60.0)), p.get("tau2_s", 500.0))
    acc0_g = np.where(pos[:, None] == 0, [0.012, -0.008, 1.0], [-0.010, 0.015, -1.0])
    tdb = np.array([0.25, -0.18, 0.32])  # mg/C
    tdsf = np.array([120.0, -80.0, 150.0])  # ppm/C
    dt_mems = (mems - 25.0)[:, None]
    acc_mg = 1000.0 * acc0_g + dt_mems * (tdb + tdsf * acc0_g * 1e-3)
    amp = np.array([1.0, -0.8, 1.2]) * p.get("scale", 1.0)
    if effect == "relay":
        acc_mg += relay(die, p.get("width_c", 4.0))[:, None] * amp
    elif effect == "backlash":
        acc_mg += backlash(die, p.get("width_c", 10.0))[:, None] * amp
    elif effect == "smooth":
        acc_mg += smooth(die, p.get("width_c", 5.0))[:, None] * amp
    elif effect == "mixture":  # two mechanisms at once: a stiff play and a slow smooth approach
        acc_mg += (0.5 * backlash(die, 3.0) + 0.6 * smooth(die, 20.0))[:, None] * amp
    elif effect == "bias2":
        acc_mg += (p.get("c2", 0.0015) * (die - 25.0) ** 2)[:, None] * np.array([1.0, -0.7, 0.9])
    elif effect == "bias3":
        acc_mg += (p.get("c3", 4e-5) * (die - 25.0) ** 3)[:, None] * np.array([1.0, -0.7, 0.9])
    acc_mg += correlated_noise(time_s.size, rng)
    temp_meas = np.round(die + 0.1 * rng.standard_normal(time_s.size))
    return DutLog(time_s=time_s, acc_g=acc_mg / 1000.0, temp_c=temp_meas,
                  meta={"serial": f"gen-{effect or 'clean'}-{seed}", "sensor": "LIS3DSH"},
                  position=pos)
