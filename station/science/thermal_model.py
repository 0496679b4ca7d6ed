"""Thermal drift model of a MEMS accelerometer axis (martinez2022 eqs. 1, 10-13).

Units: acceleration in g, temperature in C, TDB in mg/C, TDSF in ppm/C (the units of the paper's
tables and of the datasheets). Everything broadcasts over the last axis: arrays (..., 3) of
acceleration with per-axis parameters (3,), or plain scalars.
"""

from __future__ import annotations

import numpy as np

from contracts.types import T_REF_C

FULL_SCALE_MG = 2000.0  # martinez2022 eq. 12: error relative to the +-1 g working span (2000 mg)


def _per_axis(tdb_mg_per_c, tdsf_ppm_per_c) -> tuple[np.ndarray, np.ndarray]:
    return (np.asarray(tdb_mg_per_c, dtype=np.float64) * 1e-3,
            np.asarray(tdsf_ppm_per_c, dtype=np.float64) * 1e-6)


def _dt(temp_c, acc: np.ndarray, t_ref_c: float) -> np.ndarray:
    """Temperature offset shaped to broadcast against acc: (n,) temperatures meet (n, 3) samples."""
    dt = np.asarray(temp_c, dtype=np.float64) - t_ref_c
    if acc.ndim >= 1 and dt.ndim >= 1 and dt.shape == acc.shape[:-1]:
        dt = dt[..., None]
    return dt


def apply_drift(acc0_g, temp_c, tdb_mg_per_c, tdsf_ppm_per_c, t_ref_c: float = T_REF_C) -> np.ndarray:
    """Eq. 1: the reading at temp_c of an axis whose reading at t_ref_c is acc0_g.

    Acc = Acc0 + (T - T_R) (TDB + TDSF Acc0).
    """
    acc0 = np.asarray(acc0_g, dtype=np.float64)
    tdb, tdsf = _per_axis(tdb_mg_per_c, tdsf_ppm_per_c)
    dt = _dt(temp_c, acc0, t_ref_c)
    return acc0 + dt * (tdb + tdsf * acc0)


def compensate(acc_g, temp_c, tdb_mg_per_c, tdsf_ppm_per_c, t_ref_c: float = T_REF_C) -> np.ndarray:
    """Eq. 13, the exact inverse of eq. 1: Acc0 = (Acc - TDB dT) / (1 + TDSF dT)."""
    acc = np.asarray(acc_g, dtype=np.float64)
    tdb, tdsf = _per_axis(tdb_mg_per_c, tdsf_ppm_per_c)
    dt = _dt(temp_c, acc, t_ref_c)
    return (acc - tdb * dt) / (1.0 + tdsf * dt)


def drift_error_mg(section_acc_g, section_temp_c, full_range_c: float) -> np.ndarray:
    """Eq. 10: mean over consecutive thermal sections of |dAcc| scaled to the full temperature range.

    section_acc_g: (n,) or (n, 3) mean acceleration of each thermal section, in time order;
    section_temp_c: (n,) their mean temperatures; full_range_c: the studied range (70 C for the
    paper's -10..60 C chamber tests). Returns mg, per axis. Each step's change is divided by its
    own temperature change, so steps of different size weigh the same per degree.
    """
    acc = np.asarray(section_acc_g, dtype=np.float64)
    temp = np.asarray(section_temp_c, dtype=np.float64).reshape(-1)
    if acc.shape[0] != temp.shape[0] or temp.shape[0] < 2:
        raise ValueError("drift_error_mg needs at least two sections with one temperature each")
    d_acc = np.abs(np.diff(acc, axis=0))
    d_t = np.abs(np.diff(temp))
    if np.any(d_t <= 0.0):
        raise ValueError("consecutive thermal sections must differ in temperature")
    if acc.ndim > 1:
        d_t = d_t.reshape((-1,) + (1,) * (acc.ndim - 1))
    return np.mean(d_acc * (full_range_c / d_t), axis=0) * 1e3


def drift_error_fs_pct(e_mg, full_scale_mg: float = FULL_SCALE_MG):
    """Eq. 12: the drift error as a percentage of the +-1 g span (Table 7: 103.10 mg -> 5.15 %)."""
    return np.asarray(e_mg, dtype=np.float64) / full_scale_mg * 100.0


__all__ = ["apply_drift", "compensate", "drift_error_mg", "drift_error_fs_pct", "FULL_SCALE_MG"]
