"""Effect library for model diagnostics (design 7): named candidate terms beyond eq. 1.

Every effect is a term added to the baseline thermal model of martinez2022 eq. 1,

    Acc_i = Acc0_{p,i} + dT (TDB_i + TDSF_i Acc0_{p,i}) + sum_effects term_i,   dT = T - 25 C,

with the simulator's exact physics (team contract "Hidden effects"). A term is linear in its
per-axis amplitudes (solved by least squares) and may have shared nonlinear parameters (time
constants, widths) fitted by variable projection. `thermal_lag` is special: it has no amplitude,
it replaces the temperature every other term sees by a first-order lag of the measured one.

Register your own effect with `register(MyEffect())` in a Python file and pass the file with
`station diagnose --effects-file FILE` (see docs/diagnostics.md and the example
station/diagnostics/examples/my_effect.py).
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from contracts.types import StationError, T_REF_C

PPM_G_TO_MG = 1e-3  # ppm (1e-6) of an acceleration in g (1000 mg): 1e-6 * 1000 mg


@dataclass(frozen=True)
class NonlinearParam:
    """A shared (all three axes) nonlinear parameter, searched in log space when log=True."""

    name: str
    unit: str
    init: float
    lower: float
    upper: float
    log: bool = True


@dataclass
class Context:
    """What a term may depend on, for one DUT, per sample.

    dt_c is the temperature difference to 25 C that the MEMS sees: the measured (quantized) die
    temperature, or its first-order lag when `thermal_lag` is in the model. acc0_g is the current
    estimate of the true reading at 25 C (per sample: the value of the sample's orientation while
    fitting, the compensated value while compensating).
    """

    time_s: np.ndarray  # (n,)
    temp_c: np.ndarray  # (n,) measured die temperature
    temp_smooth_c: np.ndarray  # (n,) zero-phase smoothed measured temperature (quantization removed)
    dt_c: np.ndarray  # (n,) temperature seen by the MEMS minus 25 C
    acc0_g: np.ndarray  # (n, 3)
    t_power_on_s: float = 0.0
    cache: dict = field(default_factory=dict)


class Effect:
    """Base class of a candidate term.

    Subclasses set name, note (physics), needs (what data identifies it), linear (names of the
    per-axis amplitudes, each "name_unit"), nonlinear (shared NonlinearParam tuple) and implement
    columns(ctx, nl) -> array (n, 3, m): the term of axis i is columns[:, i, :] @ amplitudes[i],
    in mg. A column that is identically zero for an axis (e.g. cross_axis j == i) is not fitted.
    """

    name: str = ""
    note: str = ""
    needs: str = ""
    linear: tuple[str, ...] = ()
    nonlinear: tuple[NonlinearParam, ...] = ()
    # What to run to tell this effect apart when the data cannot (shown for unidentifiable ones).
    identify_hint: str = ""
    # Effects this one cannot be told apart from unless the data has a feature: {other: feature}.
    # Features (station.diagnostics.identifiability.data_features): "ramp_rates" = >= 2 distinct ramp rates.
    confusable_with: dict = {}

    def columns(self, ctx: Context, nl: dict[str, float]) -> np.ndarray:
        raise NotImplementedError

    def temperature(self, temp_c: np.ndarray, time_s: np.ndarray, nl: dict[str, float]) -> np.ndarray | None:
        """Temperature the MEMS sees, if this effect changes it (thermal_lag); None otherwise."""
        return None

    def describe(self) -> dict:
        return {
            "effect": self.name,
            "note": self.note,
            "needs": self.needs,
            "linear": list(self.linear),
            "nonlinear": [{"name": p.name, "unit": p.unit} for p in self.nonlinear],
        }


def _per_axis(col: np.ndarray) -> np.ndarray:
    """(n,) -> (n, 3, 1): the same regressor for every axis."""
    return np.repeat(col[:, None, None], 3, axis=1)


class BiasT2(Effect):
    name = "bias_t2"
    note = "quadratic bias drift: + c2 dT^2 (the bias curve bends; eq. 1 assumes a straight line)"
    needs = "at least 3 distinct temperatures (a ramp or 3 plateaus) in any orientation"
    identify_hint = "log at 3 or more temperature plateaus"
    linear = ("c2_mg_per_c2",)

    def columns(self, ctx, nl):
        return _per_axis(ctx.dt_c**2)


class BiasT3(Effect):
    name = "bias_t3"
    note = "cubic bias drift: + c3 dT^3 (S-shaped bias curve)"
    needs = "at least 4 distinct temperatures, ideally on both sides of 25 C"
    identify_hint = "log at 4 or more temperature plateaus"
    linear = ("c3_mg_per_c3",)

    def columns(self, ctx, nl):
        return _per_axis(ctx.dt_c**3)


class ScaleT2(Effect):
    name = "scale_t2"
    note = "quadratic scale-factor drift: + k2 dT^2 Acc0 (sensitivity curve bends with temperature)"
    needs = "at least 3 temperatures in at least 2 orientations with different Acc0 on the axis"
    identify_hint = "log 3 or more temperatures in each of 2 orientations"
    linear = ("k2_ppm_per_c2",)

    def columns(self, ctx, nl):
        return ((ctx.dt_c**2)[:, None] * ctx.acc0_g * PPM_G_TO_MG)[:, :, None]


class ThermalLag(Effect):
    name = "thermal_lag"
    note = ("the MEMS structure lags the die temperature sensor by a first-order lag tau: "
            "dT uses T_mems = lag(T_measured, tau); the output leads/lags the thermometer on ramps")
    needs = "temperature ramps; >= 2 ramp rates to tell it from hysteresis"
    identify_hint = "ramp at 2 or more different rates (lamp and chamber, or two lamp powers)"
    nonlinear = (NonlinearParam("tau_s", "s", 60.0, 1.0, 3000.0),)
    confusable_with = {"hysteresis": "ramp_rates"}

    def columns(self, ctx, nl):
        return np.zeros((ctx.time_s.shape[0], 3, 0))

    def temperature(self, temp_c, time_s, nl):
        return lag_filter(temp_c, time_s, nl["tau_s"])


class Hysteresis(Effect):
    name = "hysteresis"
    note = ("heating/cooling hysteresis: + h z, play-type state z in [-1, 1] moving toward "
            "sign(dT/dt) by |dT| / width (rate-independent)")
    needs = "heating and cooling through the same temperatures; >= 2 ramp rates to tell it from lag"
    identify_hint = "ramp at 2 or more different rates (lag scales with rate, hysteresis does not)"
    linear = ("h_mg",)
    nonlinear = (NonlinearParam("width_c", "C", 3.0, 0.2, 40.0),)

    def columns(self, ctx, nl):
        key = ("hyst_z", round(nl["width_c"], 9))
        z = ctx.cache.get(key)
        if z is None:
            z = play_state(ctx.temp_smooth_c, nl["width_c"])
            ctx.cache[key] = z
        return _per_axis(z)


class SelfHeating(Effect):
    name = "self_heating"
    note = ("warm-up transient after power-on not seen by the temperature sensor: "
            "+ w exp(-(t - t_power_on)/tau)")
    needs = "the first minutes after power-on in the log (or several power cycles)"
    identify_hint = "log from power-on"
    linear = ("w_mg",)
    nonlinear = (NonlinearParam("tau_s", "s", 300.0, 5.0, 20000.0),)

    def columns(self, ctx, nl):
        age = np.maximum(ctx.time_s - ctx.t_power_on_s, 0.0)
        return _per_axis(np.exp(-age / nl["tau_s"]))


class CrossAxis(Effect):
    name = "cross_axis"
    note = "thermal cross-axis coupling: + dT sum_{j != i} x_ij Acc0_j"
    needs = ">= 3 orientations whose Acc0_j pattern is not an affine function of Acc0_i (e.g. six-position)"
    identify_hint = "add orientations where the axes are not all equal (six-position or sfem-24) at 2 temperatures"
    linear = ("x_ppm_per_c[0]", "x_ppm_per_c[1]", "x_ppm_per_c[2]")

    def columns(self, ctx, nl):
        n = ctx.time_s.shape[0]
        out = np.zeros((n, 3, 3))
        for i in range(3):
            for j in range(3):
                if i != j:
                    out[:, i, j] = ctx.dt_c * ctx.acc0_g[:, j] * PPM_G_TO_MG
        return out


class ScaleNonlinearity(Effect):
    name = "scale_nonlinearity"
    note = "temperature drift of the 2nd-order nonlinearity: + dT n_i Acc0_i^2"
    needs = ">= 3 orientations with distinct Acc0_i (two orientations make Acc0_i^2 affine in Acc0_i)"
    identify_hint = "add a third orientation per axis (e.g. 0 g or +-1 g: six-position) at 2 temperatures"
    linear = ("n_ppm_per_c_per_g",)

    def columns(self, ctx, nl):
        return (ctx.dt_c[:, None] * ctx.acc0_g**2 * PPM_G_TO_MG)[:, :, None]


# ---------------------------------------------------------------------------------------------
# signal helpers (pure)


def lag_filter(x: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag y' = (x - y)/tau, exact for x held between samples; starts settled at x[0].

    Uses the median sample interval (logs are evenly sampled; a few lost samples barely matter).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return x.copy()
    dt = float(np.median(np.diff(time_s))) if x.size > 1 else 1.0
    a = math.exp(-max(dt, 1e-9) / max(tau_s, 1e-9))
    y, _ = lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])
    return y


def smooth_temperature(temp_c: np.ndarray, time_s: np.ndarray, window_s: float = 60.0) -> np.ndarray:
    """Zero-phase moving average: removes the 1 C quantization staircase and its dither, no lag."""
    n = temp_c.shape[0]
    if n < 3:
        return temp_c.astype(np.float64).copy()
    dt = float(np.median(np.diff(time_s)))
    w = max(1, int(round(window_s / max(dt, 1e-9))))
    if w <= 1:
        return temp_c.astype(np.float64).copy()
    half = w // 2
    padded = np.concatenate([np.full(half, temp_c[0]), temp_c, np.full(w - half - 1, temp_c[-1])])
    c = np.concatenate([[0.0], np.cumsum(padded, dtype=np.float64)])
    return (c[w:] - c[:-w]) / w


def play_state(temp_c: np.ndarray, width_c: float, decimate: int = 16, deadband_c: float = 0.1) -> np.ndarray:
    """Play-type hysteresis state z(t), z' = (sign(dT/dt) - z) |dT/dt| / width, z(0) = 0.

    Exact per step: z <- s + (z - s) exp(-|dT|/width). The input is the smoothed measured
    temperature; a backlash of deadband_c first removes its residual noise wiggles, which would
    otherwise (summed over an hour-long plateau) pull z toward 0 while the true die temperature
    moves monotonically. Computed on every `decimate`-th sample and interpolated back.
    """
    n = temp_c.shape[0]
    if n == 0:
        return np.zeros(0)
    idx = np.arange(0, n, max(1, decimate))
    if idx[-1] != n - 1:
        idx = np.append(idx, n - 1)
    t = temp_c[idx]
    zk = np.empty(idx.shape[0])
    z = 0.0
    zk[0] = 0.0
    y = float(t[0])
    half = deadband_c / 2.0
    w = max(width_c, 1e-9)
    for k in range(1, t.shape[0]):
        tk = t[k]
        if tk > y + half:
            d = tk - half - y
            y = tk - half
            z = 1.0 + (z - 1.0) * math.exp(-d / w)
        elif tk < y - half:
            d = y - (tk + half)
            y = tk + half
            z = -1.0 + (z + 1.0) * math.exp(-d / w)
        zk[k] = z
    return np.interp(np.arange(n), idx, zk)


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


BUILTIN = (BiasT2(), BiasT3(), ScaleT2(), ThermalLag(), Hysteresis(), SelfHeating(), CrossAxis(),
           ScaleNonlinearity())
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
    "load_effects_file", "lag_filter", "play_state", "smooth_temperature", "T_REF_C",
]
