"""The Effect interface every candidate term implements (built-in or a user's plug-in): its
nonlinear parameters, the context a term may depend on, and the base classes.

Why a module of its own: the library's terms live in two modules (effects.py: temperature terms
and the registry; effects_beyond_temperature.py: rate, time and static terms) that both build on
these classes; keeping them here keeps the imports one way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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
    # a discrete parameter (an effect family's shape): its value is an index into choices
    choices: tuple[str, ...] = ()
    # active only when the effect's discrete parameter takes one of these choices (else ignored)
    only_for: tuple[str, ...] = ()
    # points of the coarse profile grid the fit starts from (a rough objective needs more)
    grid: int = 7


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

    # the term's shape in words (a family overrides shape() with the shape its fit chose)
    shape_text: str = ""
    # True: the term may be evaluated at the 10 s block means of time and temperature (it is smooth
    # on that scale: every built-in). False (a user's effect, by default): it is evaluated sample by
    # sample and averaged over each block, exact for any term but ~30x slower.
    block_level: bool = False

    def columns(self, ctx: Context, nl: dict[str, float]) -> np.ndarray:
        raise NotImplementedError

    def choice(self, nl: dict[str, float]) -> str | None:
        """The chosen shape of a family (its discrete parameter), None for a single-shape effect."""
        for p in self.nonlinear:
            if p.choices:
                k = int(round(nl.get(p.name, p.init)))
                return p.choices[min(max(k, 0), len(p.choices) - 1)]
        return None

    def active(self, nl: dict[str, float]) -> list[NonlinearParam]:
        """The continuous nonlinear parameters in play for the shape chosen in nl."""
        c = self.choice(nl)
        return [p for p in self.nonlinear if not p.choices and (not p.only_for or c in p.only_for)]

    def n_nonlinear(self, nl: dict[str, float]) -> int:
        """Parameters the fit chose beyond the linear amplitudes: the active continuous ones plus
        one per discrete choice (choosing a family's shape is a fitted parameter, and the evidence
        gate charges it as one)."""
        return len(self.active(nl)) + sum(1 for p in self.nonlinear if p.choices)

    def shape(self, nl: dict[str, float]) -> str:
        """The fitted term's shape in words, with its nonlinear values."""
        vals = ", ".join(f"{p.name} {nl[p.name]:.3g} {p.unit}".rstrip() for p in self.active(nl) if p.name in nl)
        return ", ".join(x for x in (self.choice(nl) or self.shape_text, vals) if x)

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


class BuiltinEffect(Effect):
    """The library's effects: smooth within a 10 s block, so evaluated at the block means."""

    block_level = True


def _per_axis(col: np.ndarray) -> np.ndarray:
    """(n,) -> (n, 3, 1): the same regressor for every axis."""
    return np.repeat(col[:, None, None], 3, axis=1)


__all__ = ["PPM_G_TO_MG", "NonlinearParam", "Context", "Effect", "BuiltinEffect", "_per_axis"]
