"""Effects beyond temperature: the rate of temperature change (a thermal gradient across the
package, a temperature sensor that lags the die), time (a shock, a slow drift) and the acceleration
itself (a static g^2 term).

Why a module of its own: effects.py holds the Effect interface, the temperature terms and the
registry; these terms need their own helpers (a quantization-free temperature rate, the blocks'
time intervals for a step inside a block), and effects.py registers them with the others.
"""

from __future__ import annotations


import numpy as np

from station.diagnostics.effect_base import BuiltinEffect, Context, NonlinearParam, _per_axis
from station.diagnostics.operators import smooth_temperature

# ---------------------------------------------------------------------------------------------
# effects of the rate of temperature change, of time, and of the acceleration itself

# The rate dT/dt is taken from the measured temperature smoothed twice by a zero-phase moving
# average of RATE_SMOOTH_S (a triangular kernel): the 1 C quantization of a LIS3DSH's sensor makes
# the raw derivative a train of spikes, and a single moving average leaves the difference of two
# quantized samples (a plateau dithering between two degrees reads as spikes of 0.5 C/min, 0.25 C/min
# rms at 1 Hz); the second pass brings that to 0.04 C/min rms. Ramp corners are rounded over
# +-RATE_SMOOTH_S. 2 min: a whole number of the quantization's steps at 1, 0.5 (and 2, 4) C/min, and
# on the tests' plant it fits sensor_lag as well as 1 min and bias_rate better than 5 min.
RATE_SMOOTH_S = 120.0


def temperature_rate(temp_c: np.ndarray, time_s: np.ndarray, window_s: float = RATE_SMOOTH_S) -> np.ndarray:
    """dT/dt (C/s) of a measured temperature, quantization smoothed out (zero phase, no lag)."""
    temp_c = np.asarray(temp_c, np.float64)
    if temp_c.shape[0] < 3:
        return np.zeros_like(temp_c)
    s = smooth_temperature(smooth_temperature(temp_c, time_s, window_s), time_s, window_s)
    return np.gradient(s, time_s)


def _cached_rate(ctx: "Context") -> np.ndarray:
    """dT/dt of the measured temperature in C/min, computed once per prepared log (ctx.cache)."""
    rate = ctx.cache.get("bias_rate.rate_c_per_min")
    if rate is None:
        rate = ctx.cache["bias_rate.rate_c_per_min"] = temperature_rate(ctx.temp_c, ctx.time_s) * 60.0
    return rate


class BiasRate(BuiltinEffect):
    name = "bias_rate"
    note = ("bias driven by the rate of temperature change: + r_i dT/dt (during a ramp the package is not "
            "isothermal; the thermal gradient across it stresses the MEMS in proportion to the rate)")
    needs = ("temperature ramps, heating and cooling (dT/dt of both signs); to tell it from a lag: ramps in "
             "orientations with different Acc0 or holds after the ramps")
    identify_hint = ("ramp up and down; a lag (thermal_lag, sensor_lag) scales with each axis' drift "
                     "TDB + TDSF Acc0 and settles exponentially after a ramp stops, a rate bias does neither")
    shape_text = "proportional to dT/dt"
    linear = ("r_mg_per_c_per_min",)
    # at one ramp rate r dT/dt is a constant of the ramp's sign, as a hysteresis state is on a ramp
    confusable_with = {"hysteresis": "ramp_rates"}

    def columns(self, ctx, nl):
        return _per_axis(_cached_rate(ctx))


SENSOR_LAG_TAU_S = (5.0, 1200.0)  # a sensor a few mm from the MEMS in the same die or package


class SensorLag(BuiltinEffect):
    """The temperature sensor lags the die the MEMS is on: T_meas = lag(T_die, tau), so the MEMS
    sees T_die = T_meas + tau dT_meas/dt (the exact inverse of a first-order lag). The opposite case,
    the MEMS lagging the sensor, is thermal_lag; together they cover a sensor that leads or lags."""

    name = "sensor_lag"
    note = ("the temperature sensor lags the die (a first-order lag tau): the MEMS sees T_die = T_meas + "
            "tau dT_meas/dt and eq. 1's drift term uses T_die. A constant offset or a gain error of the "
            "sensor needs no parameter: Acc0 and TDB (and TDSF) of eq. 1 absorb them. A sensor that leads "
            "the MEMS is thermal_lag")
    needs = "temperature ramps; >= 2 ramp rates to tell it from hysteresis"
    identify_hint = "ramp at 2 or more different rates (lamp and chamber, or two lamp powers)"
    nonlinear = (NonlinearParam("tau_s", "s", 60.0, *SENSOR_LAG_TAU_S),)
    confusable_with = {"hysteresis": "ramp_rates"}

    def columns(self, ctx, nl):
        return np.zeros((ctx.time_s.shape[0], 3, 0))

    def temperature(self, temp_c, time_s, nl):
        return np.asarray(temp_c, np.float64) + nl["tau_s"] * temperature_rate(temp_c, time_s)

    def shape(self, nl):
        return f"sensor lags the die, tau {nl['tau_s']:.3g} s (MEMS sees T + tau dT/dt)"


def _row_intervals(time_s: np.ndarray, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """The time interval each row stands for: a sample its sample interval, a 10 s fit block its
    block. Edges halfway to the neighbours, at most half the typical spacing from the row's own time
    (a gap or a short block at a segment's end is not widened into its neighbour)."""
    iv = cache.get("bias_step.row_intervals")
    if iv is None or iv[0].shape != time_s.shape:
        t = np.asarray(time_s, np.float64)
        if t.shape[0] < 2:
            half = np.full(t.shape, 0.5)
            iv = (t - half, t + half)
        else:
            gap = np.diff(t)
            h = 0.5 * float(np.median(gap))
            lo = t - np.minimum(np.concatenate([[2 * h], gap]) / 2.0, h)
            hi = t + np.minimum(np.concatenate([gap, [2 * h]]) / 2.0, h)
            iv = (lo, hi)
        cache["bias_step.row_intervals"] = iv
    return iv


class BiasStep(BuiltinEffect):
    """A bias step at an unknown time: + s_i 1(t > t_step).

    The nonlinear parameter is the step's place in the log, t_step_pct percent of the log's time
    span (the bounds of a nonlinear parameter cannot depend on the data). columns() records the
    step time itself, t_step_h (hours on the log's clock), in the parameters it is given, for the
    report and the saved model (a derived value: the fit varies t_step_pct only).

    A step is not smooth within a 10 s block, yet the term stays block-level (fast): each row is
    the fraction of its time interval after the step (a sample: its sample interval; a block: the
    block's span, edges halfway to the neighbouring blocks), which is the exact block mean of the
    per-sample term for every full block, and makes the fit's objective continuous in the step time
    (the coarse grid, 1 % of the span apart, then Brent find it to within a block). The span's end
    is the last row's interval end, known from the blocks to within the last block's shortfall (up
    to 5 s, so a per-sample prediction may place the step up to a few seconds from the fit's)."""

    name = "bias_step"
    note = ("bias step at an unknown time: + s_i 1(t > t_step) (a mechanical shock, the board knocked or "
            "re-seated, a solder joint or die attach giving way)")
    needs = "data of the same orientation on both sides of the step (a step at an orientation change is Acc0's)"
    identify_hint = "log the orientation through the suspected event, or repeat the profile after it"
    linear = ("s_mg",)
    nonlinear = (NonlinearParam("t_step_pct", "% of the log span", 50.0, 2.0, 98.0, log=False, grid=95),)

    def columns(self, ctx, nl):
        lo, hi = _row_intervals(ctx.time_s, ctx.cache)
        ts = float(lo[0]) + nl["t_step_pct"] / 100.0 * float(hi[-1] - lo[0])
        nl["t_step_h"] = ts / 3600.0
        return _per_axis(np.clip((hi - ts) / (hi - lo), 0.0, 1.0))

    def shape(self, nl):
        pct = f"{nl['t_step_pct']:.3g} % of the log"
        if "t_step_h" in nl:
            return f"step at t = {nl['t_step_h']:.3g} h ({pct})"
        return f"step at {pct}"


class TimeDrift(BuiltinEffect):
    """A family of two shapes: linear in time, or saturating (an exponential approach from the start
    of the log, as moisture diffuses into a package or a mounting stress relaxes). A saturating drift
    with a time constant far beyond the log is a linear one, so the linear shape is kept unless the
    curvature earns its parameter."""

    name = "time_drift"
    note = ("slow drift in time, not temperature: + d_i (t - t_mid) (linear: aging, a creeping mount) or "
            "+ d_i (1 - exp(-(t - t0)/tau)) (saturating: humidity uptake of the package, relaxation of mounting "
            "stress); t_mid is the middle of the log, t0 its start")
    needs = "the same temperatures revisited at different times (repeated cycles or plateaus)"
    identify_hint = "repeat the thermal cycle, or return to 25 C at the start, middle and end of the log"
    linear = ("d_mg_per_h",)
    nonlinear = (NonlinearParam("shape", "", 0.0, 0.0, 1.0, log=False, choices=("linear in time", "saturating")),
                 NonlinearParam("tau_s", "s", 7200.0, 900.0, 72000.0, only_for=("saturating",)))

    def columns(self, ctx, nl):
        t = ctx.time_s
        t0, t1 = float(t[0]), float(t[-1])
        if self.choice(nl) == "saturating":
            tau = float(nl.get("tau_s", 7200.0))
            # scaled so that d_mg_per_h is the initial slope, as for the linear shape
            return _per_axis(-np.expm1(-(t - t0) / tau) * tau / 3600.0)
        return _per_axis((t - 0.5 * (t0 + t1)) / 3600.0)


class StaticNonlinearity(BuiltinEffect):
    name = "static_nonlinearity"
    note = ("static 2nd-order (g^2) nonlinearity: + n_i Acc0_i^2, not multiplied by dT. The baseline fits a "
            "free Acc0 per orientation, which absorbs any static function of it: identifiable only "
            "when the orientations' true accelerations are known")
    needs = ("orientations whose true acceleration is known, not fitted (a calibrated dividing head or "
             "tilt table), or several accelerations per orientation (a centrifuge)")
    identify_hint = ("log orientations of known gravity vector (calibrated dividing head / tilt table at "
                     "several angles, e.g. 0, +-30, +-60, +-90 deg per axis) and fit Acc0 from the angles, or "
                     "a centrifuge (accelerations beyond 1 g); a free Acc0 per orientation absorbs it")
    shape_text = "Acc0 squared, static"
    linear = ("n_mg_per_g2",)

    def columns(self, ctx, nl):
        return (ctx.acc0_g**2)[:, :, None]
