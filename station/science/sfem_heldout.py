"""Held-out RMSE of an SFEM fit: how well it predicts |a| = 1 g on data it never saw.

Why a module of its own: the in-sample "after" RMSE of a fit says little when the fit has about as
many parameters as residuals (six positions for twelve parameters: near zero by construction).
An honest figure needs fits of part of the data tested on the rest, which is a use of the fit, not
a part of it, and it needs the averaged positions with their sample spans.
"""

from __future__ import annotations

import numpy as np

from station.science.sfem import MIN_POSITIONS_NORM_ONLY, MIN_POSITIONS_REFERENCE, _rms, fit_sfem
from station.science.sfem_model import SfemInsufficientData
from station.science.sfem_positions import PositionSet


def heldout_rmse(acc: np.ndarray, ps: PositionSet, norm_only: bool, ref_sigma_deg: float,
                 acc_g_per_raw: float) -> tuple[float | None, str | None]:
    """Held-out |a| - 1 g RMSE of an SFEM step, in mg.

    With one position more than the fit needs: leave one position out (each predicted by a fit of
    the others). Otherwise (six positions for the 12-parameter reference fit: the in-sample "after"
    is near zero by construction) held-out halves: fit the first half of every static interval,
    test on the second half, and the other way round.
    """
    need = MIN_POSITIONS_NORM_ONLY if norm_only else MIN_POSITIONS_REFERENCE
    m = len(ps)
    ref = None if norm_only else ps.ref_dir
    res = []
    try:
        if m - 1 >= need:
            for i in range(m):
                keep = np.arange(m) != i
                f = fit_sfem(ps.mean[keep], None if ref is None else ref[keep], noise_g=ps.noise_g[keep],
                             ref_sigma_deg=ref_sigma_deg, raw_per_g=1.0 / acc_g_per_raw)
                res.append((np.linalg.norm(f.apply(ps.mean[i]) * 1.0) - 1.0) * 1e3)
            return _rms(np.asarray(res)), "leave one position out"
        halves = []
        for spans in ps.spans:
            idx = np.concatenate([np.arange(a, b) for a, b in spans])
            if idx.size < 4:
                return None, None
            h = idx.size // 2
            halves.append((acc[idx[:h]].mean(axis=0), acc[idx[h:]].mean(axis=0)))
        u1 = np.array([a for a, _ in halves])
        u2 = np.array([b for _, b in halves])
        for fit_on, test_on in ((u1, u2), (u2, u1)):
            f = fit_sfem(fit_on, ref, noise_g=ps.noise_g * np.sqrt(2.0), ref_sigma_deg=ref_sigma_deg,
                         raw_per_g=1.0 / acc_g_per_raw)
            res.extend((np.linalg.norm(f.apply(test_on), axis=1) - 1.0) * 1e3)
        return _rms(np.asarray(res)), "held-out halves (fit on one half of every static interval, tested on the other)"
    except SfemInsufficientData:
        return None, None


__all__ = [
    "heldout_rmse",
]
