"""What an SFEM fit's residuals say: how far the fixture's directions scatter, and whether the
model describes the part (pure: a fit and its positions in, numbers and words out).

Why a module of its own: the fit (station/science/sfem.py) weighs each position by the noise
figures it is given and reports sigmas that are only as honest as those figures. Two of them are
assumptions unless the data check them, and this module checks both on the step itself:

1. The reference directions' error (`ref_sigma_deg`). It enters the fit as the direction weight
   1 / sqrt(sigma_ref^2 + sigma_i^2) and so sets the sigma of the misalignment M and of A's
   off-diagonal terms (with >= 9 positions the gravity norm pins b, C and S, so the directions
   only set M). An assumed 1 deg made those sigmas ~100x too large on the simulator, whose fixture
   is exact (RMS err/sigma 0.01), and no single default suits both a machined fixture (hundredths
   of a degree) and a plate turned by hand (tenths to degrees). With >= 9 positions the step
   measures it: the direction residuals have 2 m - 3 degrees of freedom (two per position, less
   the three of M), so sigma_ref^2 = sum(angle_i^2) / (2 m - 3) - mean(sigma_i^2), floored at 0
   (`reference_scatter_deg`). With fewer positions (a six-position set) the directions also carry
   C and S and cannot be told apart from the fixture's error; the profile's `sfem_ref_sigma_deg`,
   else the documented default sfem.DEFAULT_REF_SIGMA_DEG (1 deg), is used, and the fit says so.

2. The noise of each position mean (white noise: sample std / sqrt(n)). The |a| - 1 g residuals
   have m - 9 degrees of freedom; `residual_ratio` = sqrt(chi^2 / dof) is 1 for a complete model
   and white noise. A part's bias wander between positions (flicker, random walk) raises it: on the
   simulator, parts of the LIS3DSH class with their wander read 1.2-4.4 (white-noise parts
   0.8-1.3). A static g^2 nonlinearity of 1 mg/g^2 reads ~10, 2 mg/g^2 ~20. Whatever the cause,
   the sigmas are then scaled by the ratio (the fit is redone with every position's noise times
   the ratio: the Birge ratio), so they cover what the white-noise budget misses.

The mark (`GOF_MARK_RATIO` = 5): above it the fit says in words that the model misses an effect,
and tries to name it: the residual is regressed on the norm model's own tangent (bias ~ g_i,
scale ~ g_i^2, non-orthogonality ~ g_i g_j) plus a candidate's signature, a static second-order
nonlinearity (raw_i += k_i g_i^2 shows in |a| as sum k_i g_i^3) or a third-order one (sum k_i
g_i^4); a candidate that removes >= 80 % of the excess and brings the ratio under the mark is
named with its size. Why 5: above the 4.4 the simulator's noisiest clean parts reach, below the
~10 of a 1 mg/g^2 nonlinearity. Why a mark and not a fail: the ratio is relative to the part's
noise, so a quiet part with a missing effect far inside any accuracy spec would read as high as a
noisy part with a large one; what the product cares about is the size (the held-out RMSE in mg,
a measurement a product may limit), and the verdict marks the ratio beside it (docs/verdicts.md).
"""

from __future__ import annotations

import math

import numpy as np

from station.science.sfem import MIN_POSITIONS_NORM_ONLY
from station.science.sfem_model import SfemFit, SfemGoodness

GOF_MARK_RATIO = 5.0  # residual / noise above which the model is said to miss an effect (module doc)
GOF_OK_RATIO = 1.5  # below it: "the model explains the data" (chi^2 of 15 dof rarely reaches 1.5^2 by chance)
NORM_PARAMETERS = 9  # b, C and S: what the gravity norm determines
MIN_GOF_DOF = 3  # fewer degrees of freedom: not testable
NAMED_EXCESS_SHARE = 0.8  # a named effect must remove this share of the excess chi^2
# candidate effects: name, the signature in |a| - 1 g per axis (a function of the unit direction), unit
CANDIDATES = (
    ("a second-order (g^2) nonlinearity", lambda g: g**3, "mg/g^2"),
    ("a third-order (g^3) nonlinearity", lambda g: g**4, "mg/g^3"),
)


def reference_scatter_deg(fit: SfemFit, noise_g: np.ndarray) -> tuple[float | None, int]:
    """The fixture's direction error measured on the step (module doc, 1): (sigma_ref in deg,
    degrees of freedom); (None, 0) when the step cannot tell (norm-only, or fewer than 9 positions)."""
    ang = fit.residual_direction_deg
    m = fit.n_positions
    if ang is None or m < MIN_POSITIONS_NORM_ONLY:
        return None, 0
    dof = 2 * m - 3
    s2 = float(np.sum(np.radians(np.asarray(ang)) ** 2)) / dof - float(np.mean(np.square(noise_g)))
    return math.degrees(math.sqrt(max(s2, 0.0))), dof


def _tangent(g: np.ndarray) -> np.ndarray:
    """Columns of the norm model's linearised sensitivities at unit directions g (m, 3)."""
    x, y, z = g.T
    return np.column_stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])


def _chi2_after(y: np.ndarray, cols: np.ndarray) -> tuple[float, int, np.ndarray]:
    """chi^2 left after a weighted linear fit (y and cols already divided by sigma), its rank, coefs."""
    coef, _, rank, _ = np.linalg.lstsq(cols, y, rcond=None)
    r = y - cols @ coef
    return float(r @ r), int(rank), coef


def goodness_of_fit(fit: SfemFit, mean: np.ndarray) -> SfemGoodness:
    """The residual of `fit` (at its position means `mean`, raw units) against the noise the fit
    was weighted with (module doc, 2), with words and, above the mark, a named effect if one fits."""
    m = fit.n_positions
    dof = m - NORM_PARAMETERS
    if dof < MIN_GOF_DOF:
        return SfemGoodness(None, max(dof, 0), GOF_MARK_RATIO, False,
                            f"not testable: {m} positions leave {max(dof, 0)} degrees of freedom to test the "
                            "model against the noise (needs 12 or more)")
    sig = np.asarray(fit.noise_g, dtype=np.float64)
    y = np.asarray(fit.residual_norm_mg) * 1e-3 / sig
    chi2 = float(y @ y)
    ratio = math.sqrt(chi2 / dof)
    if ratio <= GOF_MARK_RATIO:
        words = (f"residual {ratio:.1f} x the noise: the model explains the data" if ratio <= GOF_OK_RATIO else
                 f"residual {ratio:.1f} x the white noise: bias wander between positions or a small unmodelled "
                 "effect; sigmas scaled by it")
        return SfemGoodness(ratio, dof, GOF_MARK_RATIO, False, words)
    v = fit.apply(mean)
    g = v / np.linalg.norm(v, axis=1)[:, None]
    base = _tangent(g) / sig[:, None]
    chi2_base, rank_base, _ = _chi2_after(y, base)
    best = None
    for name, signature, unit in CANDIDATES:
        cols = np.column_stack([base, signature(g) / sig[:, None]])
        c2, rank, coef = _chi2_after(y, cols)
        dof_c = m - NORM_PARAMETERS - (rank - rank_base)
        if rank - rank_base < 3 or dof_c < MIN_GOF_DOF:
            continue  # the positions cannot tell this effect from the model's own parameters
        if best is None or c2 < best[1]:
            best = (name, c2, dof_c, coef[-3:] * 1e3, unit)
    words = f"residual {ratio:.1f} x the noise: the model misses an effect"
    if best is not None:
        name, c2, dof_c, size, unit = best
        ratio_c = math.sqrt(c2 / dof_c)
        if chi2 - c2 >= NAMED_EXCESS_SHARE * (chi2 - dof) and ratio_c < GOF_MARK_RATIO:
            sizes = ", ".join(f"{s:+.2g}" for s in size)
            words += (f"; {name} of about {sizes} {unit} (x, y, z) explains it (residual {ratio_c:.1f} x the "
                      "noise with it); sigmas scaled by the residual")
            return SfemGoodness(ratio, dof, GOF_MARK_RATIO, True, words, name,
                                tuple(float(s) for s in size), ratio_c)
    words += ("; no effect the station names (g^2 or g^3 nonlinearity) explains it; sigmas scaled by the "
              "residual")
    return SfemGoodness(ratio, dof, GOF_MARK_RATIO, True, words)


__all__ = [
    "GOF_MARK_RATIO",
    "goodness_of_fit",
    "reference_scatter_deg",
]
