"""Effect library for model diagnostics (design 7): named candidate terms beyond eq. 1.

Every effect is a term added to the baseline thermal model of martinez2022 eq. 1,

    Acc_i = Acc0_{p,i} + dT (TDB_i + TDSF_i Acc0_{p,i}) + sum_effects term_i,   dT = T - 25 C,

with the simulator's exact physics (team contract "Hidden effects"). A term is linear in its
per-axis amplitudes (solved by least squares) and may have shared nonlinear parameters (time
constants, widths) fitted by variable projection. `thermal_lag` is special: it has no amplitude,
it replaces the temperature every other term sees by a lag of the measured one; `sensor_lag`, its
opposite (the sensor lagging the die), replaces it by T + tau dT/dt.

Families: an effect may have a discrete nonlinear parameter (NonlinearParam.choices), its shape.
The fit tries every shape and keeps the one the data support; the report names it (Effect.shape).
`hysteresis` is a family of rate-independent operators (relay with a switching threshold,
backlash/play, smooth approach: Prandtl-Ishlinskii/Preisach elements) and `thermal_lag` one of
first- and second-order lags (die, die + package). A family is one candidate for the ranking and
the false-discovery budget, and the gate charges its shape choice as one parameter.

Register your own effect with `register(MyEffect())` in a Python file and pass the file with
`station diagnose --effects-file FILE` (see docs/diagnostics.md and the example
station/diagnostics/examples/my_effect.py).
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np

from contracts.types import StationError, T_REF_C
from station.diagnostics.operators import hysteresis_state, lag_filter, smooth_temperature

from station.diagnostics.effect_base import (  # noqa: F401  (the interface, re-exported: plug-ins import it from here)
    PPM_G_TO_MG, BuiltinEffect, Context, Effect, NonlinearParam, _per_axis,
)


class BiasT2(BuiltinEffect):
    name = "bias_t2"
    note = "quadratic bias drift: + c2 dT^2 (the bias curve bends; eq. 1 assumes a straight line)"
    needs = "at least 3 distinct temperatures (a ramp or 3 plateaus) in any orientation"
    identify_hint = "log at 3 or more temperature plateaus"
    shape_text = "quadratic in dT"
    linear = ("c2_mg_per_c2",)

    def columns(self, ctx, nl):
        return _per_axis(ctx.dt_c**2)


class BiasT3(BuiltinEffect):
    name = "bias_t3"
    note = "cubic bias drift: + c3 dT^3 (S-shaped bias curve)"
    needs = "at least 4 distinct temperatures, ideally on both sides of 25 C"
    identify_hint = "log at 4 or more temperature plateaus"
    shape_text = "cubic in dT"
    linear = ("c3_mg_per_c3",)

    def columns(self, ctx, nl):
        return _per_axis(ctx.dt_c**3)


class ScaleT2(BuiltinEffect):
    name = "scale_t2"
    note = "quadratic scale-factor drift: + k2 dT^2 Acc0 (sensitivity curve bends with temperature)"
    needs = "at least 3 temperatures in at least 2 orientations with different Acc0 on the axis"
    identify_hint = "log 3 or more temperatures in each of 2 orientations"
    shape_text = "quadratic in dT, times Acc0"
    linear = ("k2_ppm_per_c2",)

    def columns(self, ctx, nl):
        return ((ctx.dt_c**2)[:, None] * ctx.acc0_g * PPM_G_TO_MG)[:, :, None]


# A lag shorter than two 10 s fit blocks cannot be told from smoothing the thermometer's own
# noise and 1 C quantization (an errors-in-variables gain, not a lag): on clean fast-thermal logs a
# free tau of 1-3 s won delta BIC down to -224 and was admitted once in 8 DUTs.
LAG_MIN_S = 10.0


class ThermalLag(BuiltinEffect):
    """A family: the MEMS sees the die temperature through one first-order lag (the die) or two in
    series (die and package); the fit chooses the order the data support."""

    name = "thermal_lag"
    note = ("the MEMS structure lags the die temperature sensor: dT uses T_mems = lag(T_measured), a "
            "first-order lag tau or a second-order one (die tau, package tau2 in series); the output "
            "leads/lags the thermometer on ramps")
    needs = "temperature ramps; >= 2 ramp rates to tell it from hysteresis"
    identify_hint = "ramp at 2 or more different rates (lamp and chamber, or two lamp powers)"
    nonlinear = (NonlinearParam("order", "", 0.0, 0.0, 1.0, log=False, choices=("first-order", "second-order")),
                 NonlinearParam("tau_s", "s", 60.0, LAG_MIN_S, 3000.0),
                 NonlinearParam("tau2_s", "s", 600.0, LAG_MIN_S, 6000.0, only_for=("second-order",)))
    confusable_with = {"hysteresis": "ramp_rates"}

    def columns(self, ctx, nl):
        return np.zeros((ctx.time_s.shape[0], 3, 0))

    def temperature(self, temp_c, time_s, nl):
        t = lag_filter(temp_c, time_s, nl["tau_s"])
        if self.choice(nl) == "second-order":
            t = lag_filter(t, time_s, nl.get("tau2_s", 600.0))
        return t

    def shape(self, nl):
        if self.choice(nl) == "second-order":
            a, b = sorted((nl["tau_s"], nl.get("tau2_s", 600.0)))
            return f"second-order lag: die {a:.3g} s, package {b:.3g} s in series"
        return f"first-order lag, tau {nl['tau_s']:.3g} s"


HYSTERESIS_SHAPES = ("relay", "backlash", "smooth", "superposition")


PI_TRAVELS_C = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)  # the superposition's backlash elements


class Hysteresis(BuiltinEffect):
    """A family of rate-independent heating/cooling hysteresis operators (Prandtl-Ishlinskii /
    Preisach elements), each a state z in [-1, 1] (+1 after heating, -1 after cooling) of the
    smoothed die temperature, times an amplitude h per axis:

    - relay: switches at once after the temperature has turned back by width_c (a threshold);
    - backlash: play of total travel width_c: after a reversal z moves linearly with the
      temperature and saturates (a mechanical stop);
    - smooth: approaches the new state exponentially, 1/e per width_c of travel;
    - superposition: a Prandtl-Ishlinskii operator, backlash elements of travels 1, 2, 4, 8, 16 and
      32 C each with its own amplitude per axis: any loop whose branches bend monotonically, at the
      price of 18 amplitudes (the family's choice and the gate charge every one of them).

    The fit chooses the shape and its width (coarse grid of both, then the width refined)."""

    name = "hysteresis"
    note = ("heating/cooling hysteresis: + h z, z in [-1, 1] a rate-independent operator of the die "
            "temperature (relay with a switching threshold, backlash/play, smooth approach, or a "
            "superposition of backlash elements of 1-32 C) of width w")
    needs = "heating and cooling through the same temperatures; >= 2 ramp rates to tell it from lag"
    identify_hint = "ramp at 2 or more different rates (lag scales with rate, hysteresis does not)"
    linear = ("h_mg",) + tuple(f"h_play{w:g}c_mg" for w in PI_TRAVELS_C)
    nonlinear = (NonlinearParam("shape", "", 2.0, 0.0, 3.0, log=False, choices=HYSTERESIS_SHAPES),
                 NonlinearParam("width_c", "C", 3.0, 0.2, 40.0, grid=25, only_for=HYSTERESIS_SHAPES[:3]))

    # the operators are computed at these widths (a log grid, 4.5 % apart) and interpolated in log
    # width between them: a refit moves the width without rerunning the operator, and the
    # objective is smooth in the width for the local refine
    WIDTH_GRID_C = np.geomspace(0.2, 40.0, 121)
    TABLE_BYTES = 16 << 20  # all widths in one pass when the table fits (the 10 s fit blocks)
    CACHE_BYTES = 8 << 20  # else the states of the widths used last, up to this

    def _state(self, ctx, shape: str, k: int) -> np.ndarray:
        n = ctx.temp_smooth_c.shape[0]
        g = self.WIDTH_GRID_C
        if n * g.size * 8 <= self.TABLE_BYTES:
            table = ctx.cache.get(("hyst_table", shape))
            if table is None:
                table = ctx.cache[("hyst_table", shape)] = hysteresis_state(ctx.temp_smooth_c, ctx.time_s, g, shape)
            return table[:, k]
        # one width at a time (a long log), the recent ones kept up to CACHE_BYTES: a cache that kept
        # every width of every shape grew to 230 MB on a 200 MB log (issue 40); a state evicted is
        # computed again, the same numbers
        key = ("hyst_z", shape, k)
        order = ctx.cache.setdefault(("hyst_z_order",), [])
        z = ctx.cache.get(key)
        if z is None:
            z = ctx.cache[key] = hysteresis_state(ctx.temp_smooth_c, ctx.time_s, float(g[k]), shape)
        else:
            order.remove(key)
        order.append(key)
        while len(order) > 1 and len(order) * n * 8 > self.CACHE_BYTES:
            del ctx.cache[order.pop(0)]
        return z

    def _z(self, ctx, shape: str, width_c: float) -> np.ndarray:
        g = self.WIDTH_GRID_C
        lw = math.log(min(max(width_c, g[0]), g[-1]))
        k = min(int(np.searchsorted(np.log(g), lw, side="right")) - 1, g.size - 2)
        f = (lw - math.log(g[k])) / (math.log(g[k + 1]) - math.log(g[k]))
        if f <= 1e-12:
            return self._state(ctx, shape, k)
        return (1.0 - f) * self._state(ctx, shape, k) + f * self._state(ctx, shape, k + 1)

    def columns(self, ctx, nl):
        shape = self.choice(nl)
        out = np.zeros((ctx.time_s.shape[0], 3, len(self.linear)))
        if shape == "superposition":
            for m, w in enumerate(PI_TRAVELS_C, start=1):
                out[:, :, m] = self._z(ctx, "backlash", w)[:, None]
        else:
            out[:, :, 0] = self._z(ctx, shape, nl["width_c"])[:, None]
        return out

    def shape(self, nl):
        if self.choice(nl) == "superposition":
            return "superposition (Prandtl-Ishlinskii) of backlash elements, travels " + \
                ", ".join(f"{w:g}" for w in PI_TRAVELS_C) + " C"
        word = {"relay": "relay, switching threshold", "backlash": "backlash (play), total travel",
                "smooth": "smooth approach, 1/e width"}[self.choice(nl)]
        return f"{word} {nl['width_c']:.3g} C"


# The warm-up of a board's own dissipation (regulator, MCU, the sensor itself: tens of mW into a
# PCB of a few grams) settles with the die's time constant (seconds) up to the board's in still air
# (~10-30 min). Below 10 s the transient is over within a fit block; beyond an hour it is no longer
# a warm-up but a slow drift of the whole log (time_drift) or the chamber's own temperature.
SELF_HEATING_TAU_S = (10.0, 3600.0)


class SelfHeating(BuiltinEffect):
    name = "self_heating"
    note = ("warm-up transient after power-on not seen by the temperature sensor (the board's own "
            "dissipation heats the MEMS before the die sensor follows): + w exp(-(t - t_power_on)/tau), "
            "tau 10 s (the die) to 1 h (a board in still air settles in ~10-30 min)")
    needs = "the first minutes after power-on in the log (or several power cycles)"
    identify_hint = "log from power-on"
    shape_text = "exponential decay from power-on"
    linear = ("w_mg",)
    nonlinear = (NonlinearParam("tau_s", "s", 300.0, *SELF_HEATING_TAU_S),)

    def columns(self, ctx, nl):
        age = np.maximum(ctx.time_s - ctx.t_power_on_s, 0.0)
        return _per_axis(np.exp(-age / nl["tau_s"]))


class CrossAxis(BuiltinEffect):
    name = "cross_axis"
    note = ("temperature drift of cross-axis sensitivity / misalignment: + dT sum_{j != i} x_ij Acc0_j "
            "(the static cross-axis term is part of each orientation's Acc0; this is how it changes "
            "with temperature)")
    needs = ">= 3 orientations whose Acc0_j pattern is not an affine function of Acc0_i (e.g. six-position)"
    identify_hint = "add orientations where the axes are not all equal (six-position or sfem-24) at 2 temperatures"
    shape_text = "linear in dT, times the other axes' Acc0"
    linear = ("x_ppm_per_c[0]", "x_ppm_per_c[1]", "x_ppm_per_c[2]")

    def columns(self, ctx, nl):
        n = ctx.time_s.shape[0]
        out = np.zeros((n, 3, 3))
        for i in range(3):
            for j in range(3):
                if i != j:
                    out[:, i, j] = ctx.dt_c * ctx.acc0_g[:, j] * PPM_G_TO_MG
        return out


class ScaleNonlinearity(BuiltinEffect):
    name = "scale_nonlinearity"
    note = ("temperature drift of the 2nd-order (g^2) nonlinearity: + dT n_i Acc0_i^2 (the static g^2 "
            "term itself is static_nonlinearity, which a free Acc0 per orientation absorbs)")
    needs = ">= 3 orientations with distinct Acc0_i (two orientations make Acc0_i^2 affine in Acc0_i)"
    identify_hint = "add a third orientation per axis (e.g. 0 g or +-1 g: six-position) at 2 temperatures"
    shape_text = "linear in dT, times Acc0 squared"
    linear = ("n_ppm_per_c_per_g",)

    def columns(self, ctx, nl):
        return (ctx.dt_c[:, None] * ctx.acc0_g**2 * PPM_G_TO_MG)[:, :, None]


# ---------------------------------------------------------------------------------------------
# registry

REGISTRY: dict[str, Effect] = {}
_JUST_REGISTERED: list[str] = []


def register(effect: Effect, replace: bool = False) -> Effect:
    """Add an effect to the library (user plugins call this from their --effects-file)."""
    if not isinstance(effect, Effect):
        raise StationError(f"register(): expected an Effect instance, got {type(effect).__name__}")
    if not effect.name or not effect.name.replace("_", "").isalnum():
        raise StationError(f"register(): effect name {effect.name!r} must be a non-empty identifier")
    old = REGISTRY.get(effect.name)
    if old is not None and not replace and type(old).__qualname__ != type(effect).__qualname__:
        raise StationError(f"register(): effect {effect.name!r} is already registered")
    REGISTRY[effect.name] = effect
    _JUST_REGISTERED.append(effect.name)
    return effect


# the terms beyond temperature live in a module of their own (they build on the classes above)
from station.diagnostics.effects_beyond_temperature import (  # noqa: E402
    BiasRate, BiasStep, SensorLag, StaticNonlinearity, TimeDrift, temperature_rate,
)

BUILTIN = (BiasT2(), BiasT3(), ScaleT2(), ThermalLag(), Hysteresis(), SelfHeating(), CrossAxis(),
           ScaleNonlinearity(), BiasRate(), SensorLag(), BiasStep(), TimeDrift(), StaticNonlinearity())
for _e in BUILTIN:
    register(_e)
BUILTIN_NAMES = tuple(e.name for e in BUILTIN)


def get_effect(name: str) -> Effect:
    try:
        return REGISTRY[name]
    except KeyError:
        raise StationError(f"unknown effect {name!r} (known: {', '.join(sorted(REGISTRY))})") from None


def load_effects_file(path: str | Path) -> list[str]:
    """Import a user's Python file that calls register(...) (or defines EFFECTS = [...]).

    Returns the names it added. Any failure is a StationError naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise StationError(f"{p}: no such effects file")
    _JUST_REGISTERED.clear()
    spec = importlib.util.spec_from_file_location(f"station_user_effects_{abs(hash(str(p.resolve())))}", p)
    if spec is None or spec.loader is None:
        raise StationError(f"{p}: cannot import as a Python file")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except StationError:
        raise
    except Exception as exc:  # a user's file: report its error in one line
        raise StationError(f"{p}: error while loading effects: {type(exc).__name__}: {exc}") from None
    for eff in getattr(module, "EFFECTS", []) or []:
        if isinstance(eff, type):
            eff = eff()
        register(eff, replace=True)
    added = list(dict.fromkeys(_JUST_REGISTERED))
    if not added:
        raise StationError(f"{p}: registers no effect (call station.diagnostics.effects.register(...))")
    return added


__all__ = [
    "Effect", "NonlinearParam", "Context", "REGISTRY", "BUILTIN_NAMES", "register", "get_effect",
    "load_effects_file", "lag_filter", "hysteresis_state", "HYSTERESIS_SHAPES", "smooth_temperature", "T_REF_C",
    "temperature_rate",
]
