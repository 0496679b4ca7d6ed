"""The RMS figures every report prints: of the residual per sample, or of its 1-minute means, from
samples or from the 10 s fit blocks.

Why a module of its own: the ranking, the staircase, the held-out legs and the plots must all
compute "held-out RMS" the same way; the fit and the leftover read it from here.
"""

from __future__ import annotations

import numpy as np

from station.diagnostics.segmentation import DutData


def window_rms(d: DutData, resid_mg: np.ndarray, mask: np.ndarray | None = None,
               basis: str = "window") -> float:
    """RMS of the residual over axes: per sample, or of means over the RMS windows."""
    ok = ~np.isnan(resid_mg).any(axis=1)
    if mask is not None:
        ok &= mask
    if not ok.any():
        return float("nan")
    r = resid_mg[ok]
    if basis == "sample":
        return float(np.sqrt(np.mean(r**2)))
    wid = d.window[ok]
    cnt = np.bincount(wid).astype(float)
    sums = np.stack([np.bincount(wid, weights=r[:, i]) for i in range(3)], axis=1)
    keep = cnt > 0
    means = sums[keep] / cnt[keep, None]
    return float(np.sqrt(np.sum(cnt[keep, None] * means**2) / (3.0 * cnt[keep].sum())))


def block_rms(d: DutData, resid_block_mg: np.ndarray, basis: str = "window") -> float:
    """RMS over axes of a block-level residual (measured block mean - model), NaN blocks left out.

    window: RMS of the means over the RMS windows (whole blocks, exact). sample: the per-sample
    RMS of a model held constant over each 10 s block: the block residual plus the measurement's
    own scatter inside the block (the model moves far less than the noise in 10 s)."""
    ok = ~np.isnan(resid_block_mg).any(axis=1)
    if not ok.any():
        return float("nan")
    r = resid_block_mg[ok]
    cnt = d.block_count[ok]
    if basis == "sample":
        ss = float(np.sum(cnt[:, None] * r**2) + np.sum(d.block_ss_within[ok]))
        return float(np.sqrt(ss / (3.0 * cnt.sum())))
    wid = d.block_window[ok]
    cw = np.bincount(wid, weights=cnt)
    sums = np.stack([np.bincount(wid, weights=cnt * r[:, i], minlength=cw.size) for i in range(3)], axis=1)
    keep = cw > 0
    means = sums[keep] / cw[keep, None]
    return float(np.sqrt(np.sum(cw[keep, None] * means**2) / (3.0 * cw[keep].sum())))


__all__ = ["window_rms", "block_rms"]
