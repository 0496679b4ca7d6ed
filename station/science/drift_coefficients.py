"""TDB and TDSF from per-orientation thermal drifts: the end-of-test computation of martinez2022 3.3.

Why a module of its own: two estimators feed the same few equations. The streaming calibrator
gives two averaged segments per orientation (`result_from_segments`: TD_i by eq. 3, Acc0_i by
eq. 4), the offline fit gives TD_i and Acc0_i by regression over every stable sample
(`build_result` with their uncertainties); both end in TDSF (eq. 8), TDB (eq. 9) and the clamp of
a positive TDSF. Kept apart from the sample-by-sample state machine, the computation belongs to
neither estimator and reads as the equations it is. `InsufficientData` is raised here when the
orientations cannot separate TDB from TDSF, and by the offline fit for the same reason.

A choice the paper leaves open, made here: TD_i pairs closer than min_pair_delta_c (default
segment_delta_c / 2) are skipped.
"""

from __future__ import annotations

import math

import numpy as np

from station.science.streaming_config import StreamingConfig
from contracts.types import AXES, AxisThermal, OrientationDrift, Segment, StationError, ThermalResult


class InsufficientData(StationError):
    """The log or stream does not hold what the method needs (segments, orientations, swing)."""


def orientation_drifts(segments: list[Segment], config: StreamingConfig) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per orientation: TD_i (g/C, (3,)) and Acc0_i (g, (3,)), eqs. 3 and 4 averaged over the
    consecutive segment pairs of that orientation."""
    by_o: dict[int, list[Segment]] = {}
    for s in segments:
        by_o.setdefault(s.orientation, []).append(s)
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    min_dt = config.pair_delta_c()
    for o, segs in sorted(by_o.items()):
        tds, acc0s = [], []
        for s1, s2 in zip(segs[:-1], segs[1:]):
            d_t = s2.temp_mean_c - s1.temp_mean_c
            if abs(d_t) < min_dt:
                continue
            a1, a2 = np.asarray(s1.acc_mean_g), np.asarray(s2.acc_mean_g)
            td = (a2 - a1) / d_t  # eq. 3
            # eq. 4 gives the same Acc0 from either end of the pair; use the pair's mean point
            acc0 = (a1 + a2) / 2.0 - td * ((s1.temp_mean_c + s2.temp_mean_c) / 2.0 - config.t_ref_c)
            tds.append(td)
            acc0s.append(acc0)
        if tds:
            out[o] = (np.mean(tds, axis=0), np.mean(acc0s, axis=0))
    return out


def combine_orientations(
    td: np.ndarray, acc0: np.ndarray, td_sigma: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """TDSF (1/C) and TDB (g/C) per axis from TD_i (g/C) and Acc0_i (g), both (m, 3).

    Two orientations: eqs. 8 and 9 exactly. More: the straight line TD = TDB + TDSF Acc0 by
    (weighted, if td_sigma is given) least squares, like the paper's six-test reference (Fig. 12).
    Returns tdsf, tdb and, with td_sigma, their 1-sigma (scaled by the reduced chi-square when
    there are spare degrees of freedom and it exceeds 1).
    """
    m = td.shape[0]
    tdsf = np.empty(3)
    tdb = np.empty(3)
    s_tdsf = np.empty(3) if td_sigma is not None else None
    s_tdb = np.empty(3) if td_sigma is not None else None
    for k in range(3):
        x, y = acc0[:, k], td[:, k]
        if m == 2 and td_sigma is None:
            tdsf[k] = (y[0] - y[1]) / (x[0] - x[1])  # eq. 8
            tdb[k] = y[0] - tdsf[k] * x[0]  # eq. 9
            continue
        w = np.ones(m) if td_sigma is None else 1.0 / np.maximum(td_sigma[:, k], 1e-300) ** 2
        design = np.column_stack([np.ones(m), x])
        xtwx = design.T @ (design * w[:, None])
        cov = np.linalg.inv(xtwx)
        beta = cov @ (design.T @ (w * y))
        tdb[k], tdsf[k] = beta
        if td_sigma is not None:
            if m > 2:
                chi2 = float(np.sum(w * (y - design @ beta) ** 2) / (m - 2))
                cov = cov * max(chi2, 1.0)
            s_tdb[k] = math.sqrt(cov[0, 0])
            s_tdsf[k] = math.sqrt(cov[1, 1])
    return tdsf, tdb, s_tdsf, s_tdb


def build_result(
    method: str,
    drifts: dict[int, tuple[np.ndarray, np.ndarray]],
    config: StreamingConfig,
    n_segments: int,
    td_sigma: dict[int, np.ndarray] | None = None,
) -> ThermalResult:
    """ThermalResult from per-orientation TD_i/Acc0_i; clamps positive TDSF if configured."""
    if len(drifts) < 2:
        raise InsufficientData(
            f"{method}: need two orientations with two temperature segments each "
            f"(>= {config.pair_delta_c():g} C apart), found {len(drifts)} usable orientation(s)"
        )
    keys = sorted(drifts)
    td = np.array([drifts[o][0] for o in keys])
    acc0 = np.array([drifts[o][1] for o in keys])
    if np.any(np.ptp(acc0, axis=0) < config.orientation_delta_g / 2.0):
        raise InsufficientData(f"{method}: the orientations do not differ enough on every axis to separate TDB from TDSF")
    sig = np.array([td_sigma[o] for o in keys]) if td_sigma is not None else None
    tdsf, tdb, s_tdsf, s_tdb = combine_orientations(td, acc0, sig)
    axes: dict[str, AxisThermal] = {}
    orientations: dict[str, list[OrientationDrift]] = {}
    for k, name in enumerate(AXES):
        tdsf_ppm = float(tdsf[k] * 1e6)
        clamped = bool(config.clamp_positive_tdsf and tdsf_ppm > 0.0)
        axes[name] = AxisThermal(
            tdb_mg_per_c=float(tdb[k] * 1e3),  # eq. 9 with the fitted (unclamped) TDSF, as the paper
            tdsf_ppm_per_c=0.0 if clamped else tdsf_ppm,
            tdb_sigma_mg_per_c=None if s_tdb is None else float(s_tdb[k] * 1e3),
            tdsf_sigma_ppm_per_c=None if s_tdsf is None else float(s_tdsf[k] * 1e6),
            tdsf_clamped=clamped,
        )
        orientations[name] = [
            OrientationDrift(orientation=int(o), td_mg_per_c=float(td[i, k] * 1e3), acc0_g=float(acc0[i, k]))
            for i, o in enumerate(keys)
        ]
    return ThermalResult(method=method, axes=axes, orientations=orientations, n_segments=n_segments)


def result_from_segments(segments: list[Segment], config: StreamingConfig | None = None) -> ThermalResult:
    """The end-of-test computation of martinez2022 3.3 (Tables 1-2, eqs. 3, 4, 8, 9)."""
    cfg = config or StreamingConfig()
    return build_result("streaming", orientation_drifts(segments, cfg), cfg, len(segments))


__all__ = [
    "InsufficientData",
    "orientation_drifts",
    "combine_orientations",
    "build_result",
    "result_from_segments",
]
