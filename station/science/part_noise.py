"""The noise of THIS part, measured on its own still data, at the level its budgets use.

Why a module of its own: a coefficient's 1-sigma is what the k = 2 guard band of the verdict rests
on, and the largest term of it, the bias wander between the ambient and hot data of an orientation
(offline_fit module doc), is invisible to the fit's own scatter. A class constant (`BiasWander` of
the sensor class) gives a part 2.5x noisier than the class a band a third of what it needs and a
quiet part one three times too wide. So every part's budget is scaled to the part:

- measured: the white noise density per axis, from first differences of the still samples
  (mean square / 2, over ODR / 2; not a MAD, which the counts' LSB steps bias); thousands of samples know it to a few %. The
  batch-means "fit" term of every budget is the part's own scatter too (offline_fit).
- scaled with it: the bias wander (random walk and flicker) is the class's structure function
  times s = (the part's white density / the class's), i.e. the class's ratio of wander to white
  noise is assumed to hold for the part (a noisier front end, a noisier part). Why not measured
  directly: the wander that moves a slope acts over the tens of minutes between an orientation's
  ambient and hot data, while a part's still runs are minutes long and carry the plate's creeping
  temperature under a 1 C-step reading; measured on the simulator (fast-thermal, parts at 0.4x,
  1x and 3x of the class), the Allan excess of such runs (adjacent 30-240 s block means less the
  white part) reads 1.7-2x the class's wander level on every population, the unresolved
  temperature response swamping the wander, so it would give quiet parts the class's band again. A part whose wander is out of
  proportion to its white noise is covered only as far as this assumption holds; a line that
  sees such parts characterises them (benchmarks/coverage.py --characterise) and sets the class.
- the class constant as it is: when the still data are too short to tell (fewer than
  MIN_STILL_SAMPLES), and the result says so (`source` "class").

Pure: arrays in, a PartNoise out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from station.science.bias_wander import BiasWander
from station.science.chunked import diffs, median_into, rows_sum

MIN_STILL_SAMPLES = 500  # fewer still samples: the class constant as it is
SCALE_RANGE = (0.1, 10.0)  # a part is credited with no less than a tenth, no more than ten times its class


@dataclass(frozen=True)
class PartNoise:
    """What one part's still data say about its noise (module doc).

    wander: the BiasWander the budgets use (the class's at the part's level, or the class as it is
    when `source` is "class"); scale: the part's white density / the class's; n_still: still samples
    it was measured on; white_ug_per_sqrt_hz: per axis."""

    wander: BiasWander
    class_wander: BiasWander
    scale: float
    n_still: int
    white_ug_per_sqrt_hz: tuple[float, float, float]
    source: str  # "measured" | "class"

    def to_json(self) -> dict:
        return {"source": self.source, "class": self.class_wander.name, "scale": self.scale,
                "n_still_samples": self.n_still,
                "white_ug_per_sqrt_hz": list(self.white_ug_per_sqrt_hz),
                "wander_rw_g_per_sqrt_s": self.wander.rw_g_per_sqrt_s, "wander_flicker_g": self.wander.flicker_g}


def measure_part_noise(time_s, acc_g, runs: list[tuple[int, int]], class_wander: BiasWander) -> PartNoise:
    """PartNoise of one part from its still samples: `runs` [start, end) index ranges of still data
    (each one orientation, one placement) into time_s / acc_g (n, 3) (see module doc)."""
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    a = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    runs = [(s, e) for s, e in runs if e - s >= 3]
    nan3 = (float("nan"),) * 3
    n_still = sum(e - s for s, e in runs)
    if not runs or n_still < MIN_STILL_SAMPLES or not class_wander.white_ug_per_sqrt_hz > 0:
        return PartNoise(class_wander, class_wander, 1.0, n_still, nan3, "class")
    dts = diffs(t, runs)  # the runs' differences a piece at a time: bounded memory, numpy's own figures
    dt = median_into(dts.fill(np.empty(dts.n)))
    if not dt > 0:
        return PartNoise(class_wander, class_wander, 1.0, n_still, nan3, "class")
    d1 = diffs(a, runs)
    var_w = 0.5 * (rows_sum((d * d for d in d1.chunks()), 3) / d1.n)  # mean square, not a MAD: the counts' LSB steps bias a MAD
    white = np.sqrt(var_w) / math.sqrt(0.5 / dt) * 1e6  # (3,) ug/sqrt(Hz)
    scale = float(np.clip(float(np.mean(white)) / class_wander.white_ug_per_sqrt_hz, *SCALE_RANGE))
    part = replace(class_wander, name=f"{class_wander.name} x{scale:.2f} (measured white noise)",
                   white_ug_per_sqrt_hz=float(np.mean(white)),
                   rw_g_per_sqrt_s=class_wander.rw_g_per_sqrt_s * scale, flicker_g=class_wander.flicker_g * scale)
    return PartNoise(part, class_wander, scale, n_still, tuple(float(x) for x in white), "measured")


def wander_of_budget(uncertainty: Mapping[str, object] | None) -> BiasWander | None:
    """The BiasWander a calibration's budget used (its "uncertainty" JSON, offline_fit): the level
    measured on the part's raw still data. The verification of the same part uses it, rather than
    measuring the white noise of its compensated output again (which carries the temperature
    reading's noise times the compensation and would over-state the part). None: not in the doc."""
    if not uncertainty:
        return None
    rw, fl = uncertainty.get("wander_rw_g_per_sqrt_s"), uncertainty.get("wander_flicker_g")
    taus = uncertainty.get("wander_flicker_tau_s")
    if not isinstance(rw, (int, float)) or not isinstance(fl, (int, float)) or not (rw >= 0 and fl >= 0):
        return None
    tau = tuple(float(x) for x in taus) if isinstance(taus, (list, tuple)) and taus else (60.0, 600.0, 6000.0)
    return BiasWander(str(uncertainty.get("wander") or "calibration"), 0.0, float(rw), float(fl), tau)


__all__ = ["PartNoise", "measure_part_noise", "wander_of_budget", "MIN_STILL_SAMPLES"]
