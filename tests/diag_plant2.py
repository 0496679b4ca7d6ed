"""A second independent plant for the diagnostics benchmark (issue 38): a station-like log
generator with its own physics code, independent of drivers/sim and of
station/diagnostics/effects.py (nothing here is imported from either; the orientation codes and
their gravity vectors are the contract's, contracts/positions.py).

Station (one DUT, LIS3DSH-class, chamber only, no lamp):

- six orientations, P/N style per axis: +z, -z, +x, -x, +y, -y (position codes 6, 7, 2, 3, 4, 5;
  the gravity vector of each is known from its code);
- power-up at 25 C in +z held 20 min, then per orientation one thermal cycle 25 -> 60 -> -10 -> 25 C
  with 10 min holds at the extremes and 5 min at 25 C; chamber ramp rates +z 2, -z 1, +x 3,
  -x 1.5, +y 3, -y 2 C/min (four rates: a lag scales with the rate, hysteresis does not);
  10.6 h, 119 k samples at 3.125 Hz;
- between orientations the plate turns for 20 s: those rows are logged with position -1 (the
  daemon stores every sample of a move as -1) and the gravity vector rotates from one orientation
  to the next (the acceleration is in between, not at either);
- chamber air follows the set point ramp; the plate lags the air (first order, 90 s), the die lags
  the plate (40 s);
- the temperature sensor reads the die with 0.25 C noise and is quantised to 1 C (OUT_T);
- `hours` compresses or stretches the schedule (ramp rates x nominal/hours, holds x hours/nominal;
  moves stay 20 s), `rate_hz` sets the sample rate (3.125 Hz like the LIS3DSH, 1 Hz for fast tests).

DUT (drawn per seed): bias +-40 mg, scale error +-1 %, misalignment +-5 mrad; TDB uniform
-1.2..1.4 mg/C and TDSF uniform -500..0 ppm/C per axis. Baseline (martinez2022 eq. 1):
    Acc_i = Acc0_i + dT (TDB_i + TDSF_i Acc0_i),  dT = T_mems - 25 C,  Acc0 = b + A g

Noise, per axis (x noise_scale): white 0.7 mg per sample, bias random walk 4 ug/sqrt(s), flicker
40 ug as three Gauss-Markov processes (60, 600, 6000 s; stationary from the first sample).

Hidden effects (EFFECTS; terms in mg added per axis i, magnitudes in DEFAULTS, random sign and a
0.7..1.3 factor per axis unless said otherwise; T_die is the true die temperature):

    bias_t2              + c2_i dT^2                                 |c2| 0.6e-3 mg/C^2
    bias_t3              + c3_i dT^3                                 |c3| 5.0e-5 mg/C^3
    scale_t2             + k2_i dT^2 Acc0_i                          |k2| 1.2 ppm/C^2
    thermal_lag          T_mems = lag1(T_die, 120 s)                 (the MEMS lags the die and its sensor)
    thermal_lag2         T_mems = lag1(lag1(T_die, 30 s), 90 s)      (die, then package)
    hysteresis           + h_i relay(T_mems, 4 C)                    |h| 0.3 mg (switches after 4 C reversal)
    hysteresis_backlash  + h_i backlash(T_mems, 8 C)                 |h| 0.3 mg (play of 8 C travel)
    self_heating         + w_i exp(-(t - t_on)/1200 s)               |w| 3 mg (package stress relaxing)
    cross_axis           + dT sum_{j!=i} x_ij Acc0_j                 |x| 12 ppm/C
    scale_nonlinearity   + dT n_i Acc0_i^2                           |n| 15 ppm/C/g^2
    bias_rate            + r_i dT_die/dt                             |r| 0.15 mg/(C/min)
    sensor_lag           the temperature SENSOR reads lag1(T_die, 120 s); the MEMS sees T_die
    bias_step            + s_i H(t - t_step)                         |s| 1..2 mg, t_step in 35..65 % of the log
    time_drift           + D_i (1 - exp(-t / tau_h))                 |D| 2 mg, tau_h 2 h (humidity uptake)
    static_nonlinearity  + k_i (A g)_i^2 (static: constant per orientation) |k| 5 mg/g^2
    hvac                 + a_i f(t); f a zero-mean square wave of period 40 min (chamber fan/compressor
                         cycle) seen through the package's 120 s thermal lag, |a| 0.35 mg: forced
                         convection sets a gradient across the package that the die sensor never sees
    popcorn              + a_i s(t); s in {0, 1} a random telegraph signal (charge trap: exponential
                         dwell, mean 150 s) active in 4 bursts of 30 min, |a| 1 mg (one trap: the
                         same s on every axis)

Magnitudes: near the detection limit, each raising the control's baseline held-out RMS (1-minute
means) to about 1.4-3x (3.125 Hz and 1 Hz, 1x noise), except where the physics is given: the lags
(120 s, the die-to-MEMS and die-to-sensor lags of a LIS3DSH-class package) give 15-25x with this
population's drift (TDB + TDSF Acc0 up to ~1.5 mg/C at 1-3 C/min), bias_step is 1-2 mg.
`params={"thermal_lag": {"tau_s": 15}}` makes any of them weaker.

`static_nonlinearity` is constant within each orientation, so a baseline that fits Acc0 per
orientation absorbs it completely: on this plant it is a negative control (nothing should be
admitted), not a detectable effect. `hvac` and `popcorn` are not in the diagnostics library.

    log, truth = make_log(["bias_t2"], seed=1)       # DutLog + truth dict
    ctrl, _ = make_log([], seed=1)                   # the control twin: same DUT, same noise
    log, truth, ctrl, ctruth = make_pair(["bias_t2"], seed=1, rate_hz=1.0)
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Sequence

import numpy as np
from scipy.signal import lfilter

from contracts.logfile import DutLog
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX

RATE_HZ = 3.125  # LIS3DSH output data rate of the station
FAST_RATE_HZ = 1.0  # fast option for tests
T_REF_C = 25.0
T_HOT_C, T_COLD_C = 60.0, -10.0
POWER_UP_S = 1200.0
HOLD_EXTREME_S = 600.0
HOLD_END_S = 300.0
MOVE_S = 20.0
# (orientation, chamber ramp C/min): P/N style per axis, z first
CYCLES: tuple[tuple[str, float], ...] = (("+z", 2.0), ("-z", 1.0), ("+x", 3.0), ("-x", 1.5), ("+y", 3.0), ("-y", 2.0))
AIR_TO_PLATE_TAU_S = 90.0
PLATE_TO_DIE_TAU_S = 40.0
TEMP_NOISE_C = 0.25
TEMP_STEP_C = 1.0

WHITE_MG = 0.7
RW_MG_PER_SQRT_S = 0.004
FLICKER_MG = 0.04
FLICKER_TAU_S = (60.0, 600.0, 6000.0)

# generator name -> the library's name for the same physics (None: not in the library)
EFFECTS: dict[str, str | None] = {
    "bias_t2": "bias_t2",
    "bias_t3": "bias_t3",
    "scale_t2": "scale_t2",
    "thermal_lag": "thermal_lag",
    "thermal_lag2": "thermal_lag",
    "hysteresis": "hysteresis",
    "hysteresis_backlash": "hysteresis",
    "self_heating": "self_heating",
    "cross_axis": "cross_axis",
    "scale_nonlinearity": "scale_nonlinearity",
    "bias_rate": "bias_rate",
    "sensor_lag": "sensor_lag",
    "bias_step": "bias_step",
    "time_drift": "time_drift",
    "static_nonlinearity": "static_nonlinearity",
    "hvac": None,
    "popcorn": None,
}

# nominal magnitudes (see the module docstring for the terms)
DEFAULTS: dict[str, dict[str, float]] = {
    "bias_t2": {"c2_mg_per_c2": 0.6e-3},
    "bias_t3": {"c3_mg_per_c3": 5.0e-5},
    "scale_t2": {"k2_ppm_per_c2": 1.2},
    "thermal_lag": {"tau_s": 120.0},
    "thermal_lag2": {"tau_s": 30.0, "tau2_s": 90.0},
    "hysteresis": {"h_mg": 0.3, "width_c": 4.0},
    "hysteresis_backlash": {"h_mg": 0.3, "width_c": 8.0},
    "self_heating": {"w_mg": 3.0, "tau_s": 1200.0},
    "cross_axis": {"x_ppm_per_c": 12.0},
    "scale_nonlinearity": {"n_ppm_per_c_per_g2": 15.0},
    "bias_rate": {"r_mg_per_c_per_min": 0.15},
    "sensor_lag": {"tau_s": 120.0},
    "bias_step": {"s_min_mg": 1.0, "s_max_mg": 2.0},
    "time_drift": {"d_mg": 2.0, "tau_s": 7200.0},
    "static_nonlinearity": {"k_mg_per_g2": 5.0},
    "hvac": {"a_mg": 0.35, "period_s": 2400.0, "tau_s": 120.0},
    "popcorn": {"a_mg": 1.0, "dwell_s": 150.0, "bursts": 4.0, "burst_s": 1800.0},
}


# ---- schedule and thermal plant --------------------------------------------------------------

def nominal_hours() -> float:
    s = POWER_UP_S + MOVE_S * (len(CYCLES) - 1)
    for _, rate in CYCLES:
        s += (abs(T_HOT_C - T_REF_C) + abs(T_HOT_C - T_COLD_C) + abs(T_REF_C - T_COLD_C)) / rate * 60.0
        s += 2 * HOLD_EXTREME_S + HOLD_END_S
    return s / 3600.0


def schedule(hours: float | None = None) -> list[dict]:
    """The profile as segments {kind: hold|ramp|move, t0, t1, position (name or None), c0, c1}:
    the chamber air temperature goes linearly from c0 to c1 over [t0, t1)."""
    nom_s = nominal_hours() * 3600.0
    moves_s = MOVE_S * (len(CYCLES) - 1)
    k = 1.0 if hours is None else max((hours * 3600.0 - moves_s) / (nom_s - moves_s), 1e-3)
    segs: list[dict] = []
    t = 0.0

    def add(kind: str, dur: float, pos: str | None, c0: float, c1: float) -> None:
        nonlocal t
        segs.append({"kind": kind, "t0": t, "t1": t + dur, "position": pos, "c0": c0, "c1": c1})
        t += dur

    add("hold", POWER_UP_S * k, CYCLES[0][0], T_REF_C, T_REF_C)
    cur = T_REF_C
    for n, (pos, rate) in enumerate(CYCLES):
        if n:
            add("move", MOVE_S, None, cur, cur)
        for target, hold in ((T_HOT_C, HOLD_EXTREME_S), (T_COLD_C, HOLD_EXTREME_S), (T_REF_C, HOLD_END_S)):
            add("ramp", abs(target - cur) / rate * 60.0 * k, pos, cur, target)
            add("hold", hold * k, pos, target, target)
            cur = target
    return segs


def lag1(x: np.ndarray, tau_s: float, rate_hz: float) -> np.ndarray:
    """First-order lag y' = (x - y)/tau, integrated exactly for x linear between samples, y(0) = x(0).

    On a ramp of slope m the output settles to x(t) - m tau, i.e. x(t - tau)."""
    x = np.asarray(x, dtype=np.float64)
    dt = 1.0 / rate_hz
    a = math.exp(-dt / tau_s)
    g = tau_s * (1.0 - a) / dt  # y[k] = a y[k-1] + (1 - g) x[k] + (g - a) x[k-1]
    b = [1.0 - g, g - a]
    zi = [(a + b[1]) * x[0]] if x.ndim == 1 else ((a + b[1]) * x[0])[None, :]
    y, _ = lfilter(b, [1.0, -a], x, axis=0, zi=zi)
    return y


def _rotate(v: np.ndarray, axis: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """Rodrigues: rotate the vector v about the unit axis by each angle in ang -> (len(ang), 3)."""
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    return v * c + np.cross(axis, v) * s + axis * float(axis @ v) * (1.0 - c)


def plant(rate_hz: float = RATE_HZ, hours: float | None = None) -> dict[str, np.ndarray]:
    """time_s, air_c, plate_c, die_c, position (code, -1 while moving), gravity (n, 3) unit vectors
    in the DUT frame, rate_c_per_min of the die (analytic derivative of the plant)."""
    segs = schedule(hours)
    n = int(math.floor(segs[-1]["t1"] * rate_hz))
    time_s = np.arange(n) / rate_hz
    knots_t = [segs[0]["t0"]] + [s["t1"] for s in segs]
    knots_c = [segs[0]["c0"]] + [s["c1"] for s in segs]
    air = np.interp(time_s, knots_t, knots_c)
    plate = lag1(air, AIR_TO_PLATE_TAU_S, rate_hz)
    die = lag1(plate, PLATE_TO_DIE_TAU_S, rate_hz)
    pos = np.empty(n, np.int64)
    grav = np.empty((n, 3))
    for k, s in enumerate(segs):
        i0, i1 = np.searchsorted(time_s, [s["t0"], s["t1"]])
        if s["kind"] != "move":
            pos[i0:i1] = POSITION_INDEX[s["position"]]
            grav[i0:i1] = GRAVITY_DIRECTIONS[POSITION_INDEX[s["position"]]]
            continue
        pos[i0:i1] = -1
        a = GRAVITY_DIRECTIONS[POSITION_INDEX[segs[k - 1]["position"]]]
        b = GRAVITY_DIRECTIONS[POSITION_INDEX[segs[k + 1]["position"]]]
        ax = np.cross(a, b)
        if np.linalg.norm(ax) < 1e-9:  # a flip (+z -> -z): turn about an axis perpendicular to a
            ax = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        ax = ax / np.linalg.norm(ax)
        ang = math.acos(float(np.clip(a @ b, -1.0, 1.0)))
        frac = (time_s[i0:i1] - s["t0"] + 1.0 / rate_hz) / (s["t1"] - s["t0"] + 1.0 / rate_hz)
        grav[i0:i1] = _rotate(a, ax, frac * ang)
    rate = np.gradient(die, time_s) * 60.0
    return {"time_s": time_s, "air_c": air, "plate_c": plate, "die_c": die, "position": pos, "gravity": grav,
            "die_rate_c_per_min": rate}


# ---- noise -----------------------------------------------------------------------------------

def accel_noise(n: int, rate_hz: float, rng: np.random.Generator, scale: float = 1.0,
                white_mg: float = WHITE_MG, rw_mg_per_sqrt_s: float = RW_MG_PER_SQRT_S,
                flicker_mg: float = FLICKER_MG, flicker_tau_s: Sequence[float] = FLICKER_TAU_S) -> np.ndarray:
    """(n, 3) mg: white + bias random walk (from 0) + flicker (sum of stationary Gauss-Markov)."""
    dt = 1.0 / rate_hz
    out = white_mg * rng.standard_normal((n, 3))
    out += np.cumsum(rw_mg_per_sqrt_s * math.sqrt(dt) * rng.standard_normal((n, 3)), axis=0)
    sig = flicker_mg / math.sqrt(len(flicker_tau_s))
    for tau in flicker_tau_s:
        a = math.exp(-dt / tau)
        x0 = sig * rng.standard_normal(3)
        e = sig * math.sqrt(1.0 - a * a) * rng.standard_normal((n, 3))
        x, _ = lfilter([1.0], [1.0, -a], e, axis=0, zi=(a * x0)[None, :])
        out += x
    return scale * out


def allan_deviation(x: np.ndarray, rate_hz: float, m: int) -> float:
    """Overlapping Allan deviation of x (n,) at averaging time m / rate_hz (closed form check)."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    avg = (c[m:] - c[:-m]) / m
    d = avg[m:] - avg[:-m]
    return float(np.sqrt(0.5 * np.mean(d * d)))


# ---- the DUT ---------------------------------------------------------------------------------

def _rng(seed: int, stream: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(stream.encode())])


def draw_dut(seed: int) -> dict:
    r = _rng(seed, "dut")
    bias_g = r.uniform(-0.040, 0.040, 3)
    scale = r.uniform(-0.01, 0.01, 3)
    mis = r.uniform(-0.005, 0.005, (3, 3))
    np.fill_diagonal(mis, 0.0)
    return {
        "bias_g": bias_g,
        "A": np.eye(3) + np.diag(scale) + mis,  # Acc0 = b + A g (g in g units)
        "tdb_mg_per_c": r.uniform(-1.2, 1.4, 3),
        "tdsf_ppm_per_c": r.uniform(-500.0, 0.0, 3),
    }


def _signed(r: np.random.Generator, mag: float, n: int = 3) -> np.ndarray:
    return mag * r.uniform(0.7, 1.3, n) * r.choice([-1.0, 1.0], n)


def relay(temp: np.ndarray, width_c: float, start: float = -1.0) -> np.ndarray:
    """+1 once the temperature has risen width_c above its last minimum, -1 once it has fallen
    width_c below its last maximum (a switching threshold); start: the state before any switch."""
    z, hi, lo = start, temp[0], temp[0]
    out = np.empty_like(temp)
    for k, v in enumerate(temp.tolist()):
        hi, lo = max(hi, v), min(lo, v)
        if z > 0 and v < hi - width_c:
            z, lo = -1.0, v
        elif z < 0 and v > lo + width_c:
            z, hi = 1.0, v
        out[k] = z
    return out


def backlash(temp: np.ndarray, width_c: float) -> np.ndarray:
    """Play of total travel width_c: z = (T - y)/(width/2), y dragged by T at the ends of the play."""
    r = width_c / 2.0
    y = float(temp[0]) - r  # settled as after heating: z = +1
    out = np.empty_like(temp)
    for k, v in enumerate(temp.tolist()):
        y = min(max(y, v - r), v + r)
        out[k] = (v - y) / r
    return out


def _telegraph(time_s: np.ndarray, r: np.random.Generator, dwell_s: float, bursts: int, burst_s: float) -> tuple[np.ndarray, list]:
    s = np.zeros(time_s.size)
    t_end = float(time_s[-1])
    starts = np.sort(r.uniform(0.1 * t_end, 0.9 * t_end - burst_s, bursts))
    spans = []
    for t0 in starts:
        t, state = float(t0), 1.0
        t1 = t0 + burst_s
        while t < t1:
            d = float(r.exponential(dwell_s))
            if state:
                s[(time_s >= t) & (time_s < min(t + d, t1))] = 1.0
            t += d
            state = 1.0 - state
        spans.append((float(t0), float(t1)))
    return s, spans


def make_log(effects: Iterable[str] | str | None = (), seed: int = 0, rate_hz: float = RATE_HZ,
             hours: float | None = None, noise_scale: float = 1.0, params: dict | None = None,
             keep_arrays: bool = True) -> tuple[DutLog, dict]:
    """One DUT's log with the named hidden effects (EFFECTS) and the truth.

    The DUT, the noise and the temperature sensor's noise depend only on the seed (and rate, hours,
    noise_scale), each effect's random parameters on the seed and its name: the same call without
    the effects is the control twin. params: {effect: {key: value}} overrides DEFAULTS."""
    if effects is None:
        effects = ()
    if isinstance(effects, str):
        effects = [e for e in effects.replace("+", ",").split(",") if e]
    effects = list(dict.fromkeys(effects))
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown} (known: {', '.join(EFFECTS)})")
    if "thermal_lag" in effects and "thermal_lag2" in effects:
        raise ValueError("thermal_lag and thermal_lag2 are two shapes of one effect: pick one")
    p = {e: {**DEFAULTS[e], **(params or {}).get(e, {})} for e in effects}
    pl = plant(rate_hz, hours)
    time_s, die, grav, pos = pl["time_s"], pl["die_c"], pl["gravity"], pl["position"]
    n = time_s.size
    dut = draw_dut(seed)
    acc0_g = dut["bias_g"] + grav @ dut["A"].T  # (n, 3)
    truth: dict = {"seed": seed, "rate_hz": rate_hz, "hours": float(time_s[-1] / 3600.0), "n": n,
                   "noise_scale": noise_scale, "effects": {}, "library_names": {e: EFFECTS[e] for e in effects},
                   "dut": {k: np.asarray(v).tolist() for k, v in dut.items()},
                   "noise": {"white_mg": WHITE_MG * noise_scale, "rw_mg_per_sqrt_s": RW_MG_PER_SQRT_S * noise_scale,
                             "flicker_mg": FLICKER_MG * noise_scale, "flicker_tau_s": list(FLICKER_TAU_S)},
                   "temp_sensor": {"noise_c": TEMP_NOISE_C, "step_c": TEMP_STEP_C}}

    # temperatures: the MEMS sees mems_c, the sensor reads sensor_c
    mems = die
    if "thermal_lag" in effects:
        mems = lag1(die, p["thermal_lag"]["tau_s"], rate_hz)
    if "thermal_lag2" in effects:
        mems = lag1(lag1(die, p["thermal_lag2"]["tau_s"], rate_hz), p["thermal_lag2"]["tau2_s"], rate_hz)
    sensor = die
    if "sensor_lag" in effects:
        sensor = lag1(die, p["sensor_lag"]["tau_s"], rate_hz)
    dT = mems - T_REF_C
    acc_mg = 1000.0 * acc0_g + dT[:, None] * (dut["tdb_mg_per_c"] + 1e-3 * dut["tdsf_ppm_per_c"] * acc0_g)

    term = np.zeros((n, 3))
    for e in effects:
        r = _rng(seed, "effect:" + e)
        q = p[e]
        rec: dict = {k: v for k, v in q.items()}
        if e == "bias_t2":
            c = _signed(r, q["c2_mg_per_c2"])
            term += dT[:, None] ** 2 * c
            rec["c2_mg_per_c2"] = c.tolist()
        elif e == "bias_t3":
            c = _signed(r, q["c3_mg_per_c3"])
            term += dT[:, None] ** 3 * c
            rec["c3_mg_per_c3"] = c.tolist()
        elif e == "scale_t2":
            k2 = _signed(r, q["k2_ppm_per_c2"])
            term += 1e-3 * dT[:, None] ** 2 * k2 * acc0_g
            rec["k2_ppm_per_c2"] = k2.tolist()
        elif e in ("hysteresis", "hysteresis_backlash"):
            h = _signed(r, q["h_mg"])
            z = relay(mems, q["width_c"]) if e == "hysteresis" else backlash(mems, q["width_c"])
            term += z[:, None] * h
            rec["h_mg"] = h.tolist()
            rec["shape"] = "relay" if e == "hysteresis" else "backlash"
        elif e == "self_heating":
            w = _signed(r, q["w_mg"])
            term += np.exp(-time_s / q["tau_s"])[:, None] * w
            rec["w_mg"] = w.tolist()
            rec["t_power_on_s"] = 0.0
        elif e == "cross_axis":
            x = _signed(r, q["x_ppm_per_c"], 9).reshape(3, 3)
            np.fill_diagonal(x, 0.0)
            term += 1e-3 * dT[:, None] * (acc0_g @ x.T)
            rec["x_ppm_per_c"] = x.tolist()
        elif e == "scale_nonlinearity":
            nn = _signed(r, q["n_ppm_per_c_per_g2"])
            term += 1e-3 * dT[:, None] * nn * acc0_g ** 2
            rec["n_ppm_per_c_per_g2"] = nn.tolist()
        elif e == "bias_rate":
            rr = _signed(r, q["r_mg_per_c_per_min"])
            term += pl["die_rate_c_per_min"][:, None] * rr
            rec["r_mg_per_c_per_min"] = rr.tolist()
        elif e == "bias_step":
            s = r.uniform(q["s_min_mg"], q["s_max_mg"], 3) * r.choice([-1.0, 1.0], 3)
            ok = np.flatnonzero((pos >= 0) & (time_s > 0.35 * time_s[-1]) & (time_s < 0.65 * time_s[-1]))
            t_step = float(time_s[int(r.choice(ok))])
            term += (time_s >= t_step)[:, None] * s
            rec.update({"s_mg": s.tolist(), "t_step_s": t_step})
        elif e == "time_drift":
            tau_h = q["tau_s"]
            d = _signed(r, q["d_mg"])
            term += (1.0 - np.exp(-time_s / tau_h))[:, None] * d
            rec.update({"d_mg": d.tolist(), "tau_s": tau_h})
        elif e == "static_nonlinearity":
            k = _signed(r, q["k_mg_per_g2"])
            term += k * (grav @ dut["A"].T) ** 2
            rec["k_mg_per_g2"] = k.tolist()
        elif e == "hvac":
            a = _signed(r, q["a_mg"])
            phase = float(r.uniform(0.0, 1.0))
            sq = np.where(((time_s / q["period_s"] + phase) % 1.0) < 0.5, 1.0, -1.0)
            f = lag1(sq, q["tau_s"], rate_hz)
            term += (f - f.mean())[:, None] * a
            rec.update({"a_mg": a.tolist(), "phase": phase})
        elif e == "popcorn":
            a = _signed(r, q["a_mg"])
            s, spans = _telegraph(time_s, r, q["dwell_s"], int(q["bursts"]), q["burst_s"])
            term += s[:, None] * a
            rec.update({"a_mg": a.tolist(), "bursts_s": spans})
        truth["effects"][e] = rec
    acc_mg += term
    acc_mg += accel_noise(n, rate_hz, _rng(seed, "noise"), noise_scale)
    t_rng = _rng(seed, "temperature")
    temp_log = TEMP_STEP_C * np.round((sensor + TEMP_NOISE_C * t_rng.standard_normal(n)) / TEMP_STEP_C)
    if keep_arrays:
        truth["arrays"] = {"air_c": pl["air_c"], "plate_c": pl["plate_c"], "die_c": die, "mems_c": mems,
                           "sensor_c": sensor, "term_mg": term, "gravity": grav}
    log = DutLog(time_s=time_s, acc_g=acc_mg / 1000.0, temp_c=temp_log,
                 meta={"serial": f"P2-{seed:04d}", "sensor": "LIS3DSH", "source": "diag_plant2",
                       "odr_hz": f"{rate_hz:g}", "t_power_on_s": "0"},
                 position=pos.copy())
    return log, truth


def make_pair(effects: Iterable[str] | str | None = (), seed: int = 0, **kw) -> tuple[DutLog, dict, DutLog, dict]:
    """The log with the effects and its control twin (same DUT and noise realisation, no effect)."""
    log, truth = make_log(effects, seed, **kw)
    ctrl, ctruth = make_log((), seed, **kw)
    return log, truth, ctrl, ctruth


__all__ = ["EFFECTS", "DEFAULTS", "CYCLES", "RATE_HZ", "FAST_RATE_HZ", "make_log", "make_pair", "plant", "schedule",
           "lag1", "relay", "backlash", "accel_noise", "allan_deviation", "draw_dut", "nominal_hours"]
