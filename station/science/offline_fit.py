"""Offline thermal fit: regression over all stable data (the "Regr." column of martinez2022 Table 5).

Where the streaming calibrator keeps two 1000-sample averages per orientation, the offline fit
uses every sample the calibrator's gradient gate calls stable, so it sees more temperatures and
more samples (and any number of temperature steps). Per orientation (the calibrator's own
orientation counter, the same rule): acceleration = Acc0_i + TD_i (T - 25) by least squares per
axis; then TDSF/TDB from the (TD_i, Acc0_i) points: eqs. 8/9 for two orientations, a weighted
straight line for more (the paper's six-test reference, Fig. 12).

Details:
- Samples taken while the plate moves (the few samples between a turn's start and the moment the
  filtered acceleration registers it) are still "thermally stable"; they are dropped by a
  stillness test, |raw - filtered acceleration| under `still_sigma` robust noise sigmas per axis.
- The temperature reading is noisy and quantized (LIS3DSH: 1 C steps), which biases an ordinary
  least-squares slope toward zero by var(noise)/var(T) (errors in variables). The reading noise
  variance is estimated from first differences within stable runs (var(diff)/2) and removed from
  the temperature variance (a method-of-moments correction; ~0.1 % on a 25 C step).
- Uncertainty: samples are autocorrelated (slow drifts, filtering, unmodelled effects), so the
  per-sample OLS standard error would be far too small. The 1-sigma of each TD_i comes from batch
  means: the stable runs are cut into blocks of `block_samples` consecutive samples, the block means
  are regressed (weighted by block size) and the scatter of the block means about the line gives
  the slope variance. Correlation shorter than a block is thus absorbed. It is propagated to
  TDB/TDSF through the weighted line fit (scaled by the reduced chi-square when > 1 with more than
  two orientations). Acc0_i errors are neglected (micro-g against a >1 g lever).
"""

from __future__ import annotations

import numpy as np

from station.science.streaming import GateTrace, InsufficientData, StreamingConfig, build_result, trace_gate
from station.types import ThermalResult


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous [start, end) runs where mask is True."""
    if not mask.any():
        return []
    d = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist()))


def usable_mask(acc_g: np.ndarray, trace: GateTrace, still_sigma: float = 8.0, floor_g: float = 2e-4) -> np.ndarray:
    """Thermally stable (gate open) and mechanically still samples."""
    stable = trace.stable
    resid = acc_g - trace.acc_filt_g
    if stable.sum() >= 10:
        r = resid[stable]
        sigma = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    else:
        sigma = np.zeros(3)
    tol = np.maximum(still_sigma * sigma, floor_g)
    still = np.all(np.abs(resid) < tol, axis=1)
    return stable & still


def offline_fit(
    time_s,
    acc_g,
    temp_c,
    config: StreamingConfig | None = None,
    *,
    block_samples: int = 200,
    still_sigma: float = 8.0,
    min_span_c: float | None = None,
    eiv_correction: bool = True,
    trace: GateTrace | None = None,
) -> ThermalResult:
    """TDB/TDSF per axis (method "offline") with 1-sigma uncertainties.

    min_span_c: an orientation is used when its stable data spans at least this temperature range
    (default config.segment_delta_c / 2). trace: a precomputed `trace_gate` result (saves a pass).
    """
    cfg = config or StreamingConfig()
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    if trace is None:
        trace, _ = trace_gate(t, acc, temp, cfg)
    use = usable_mask(acc, trace, still_sigma)
    span_needed = cfg.pair_delta_c() if min_span_c is None else float(min_span_c)
    drifts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    sigmas: dict[int, np.ndarray] = {}
    n_runs = 0
    for o in np.unique(trace.orientation):
        mask = use & (trace.orientation == o)
        runs = [(s, e) for s, e in _runs(mask) if e - s >= 2]
        n = sum(e - s for s, e in runs)
        if n < max(cfg.average_samples, 10):
            continue
        # block means (batch means) over the stable runs of this orientation
        bx, by, bn = [], [], []
        for s, e in runs:
            nb = max(1, int(round((e - s) / block_samples)))
            for blk in np.array_split(np.arange(s, e), nb):
                bx.append(temp[blk].mean())
                by.append(acc[blk].mean(axis=0))
                bn.append(blk.shape[0])
        bx, by, bn = np.array(bx), np.array(by), np.array(bn, dtype=np.float64)
        if np.ptp(bx) < span_needed:
            continue
        if np.any(np.ptp(by, axis=0) > cfg.orientation_delta_g):
            raise InsufficientData(
                f"offline: orientation {int(o)} holds data more than {cfg.orientation_delta_g:g} g apart; "
                "the plate was turned before a segment could be logged"
            )
        n_runs += len(runs)
        idx = np.concatenate([np.arange(s, e) for s, e in runs])
        x = temp[idx] - cfg.t_ref_c
        y = acc[idx]
        xm = x.mean()
        ym = y.mean(axis=0)
        xc = x - xm
        sxx = float(xc @ xc)
        sxy = xc @ (y - ym)
        if eiv_correction:
            dtemp = np.concatenate([np.diff(temp[s:e]) for s, e in runs])
            var_noise = 0.5 * float(np.mean(dtemp * dtemp)) if dtemp.size else 0.0
            sxx_true = sxx - x.shape[0] * var_noise
            if sxx_true > 0.5 * sxx:  # only a small correction is trusted
                sxx = sxx_true
        td = sxy / sxx  # eq. 3 as a regression slope, g/C
        acc0 = ym - td * xm  # eq. 4: the line at T = t_ref
        # batch-means slope uncertainty
        m = bx.shape[0]
        if m >= 3:
            bxm = np.average(bx - cfg.t_ref_c, weights=bn)
            bxc = bx - cfg.t_ref_c - bxm
            sbxx = float(np.sum(bn * bxc * bxc))
            bym = np.average(by, axis=0, weights=bn)
            bslope = (bn * bxc) @ (by - bym) / sbxx
            resid = by - bym - np.outer(bxc, bslope)
            s2 = np.sum(bn[:, None] * resid * resid, axis=0) / (m - 2) if m > 2 else np.full(3, np.inf)
            sigmas[int(o)] = np.sqrt(s2 / sbxx)
        else:
            sigmas[int(o)] = np.full(3, np.inf)
        drifts[int(o)] = (td, acc0)
    if len(drifts) >= 2 and all(np.all(np.isfinite(sigmas[o])) for o in drifts):
        return build_result("offline", drifts, cfg, n_runs, td_sigma=sigmas)
    res = build_result("offline", drifts, cfg, n_runs)
    return res


__all__ = ["offline_fit", "usable_mask"]
