"""The station's thermal SFEM as the board's version-2 record: a cubic in temperature per element of
A and b (docs/design.md 3.1 "version-2 record"; sensors2023 eq. 8, applied on the board).

Why an approximation: the station's model (station/science/sfem_thermal.py SfemThermalModel) holds
each PARAMETER (misalignment rotation vector, non-orthogonality, scale, bias) as a polynomial of
temperature, and A = M C S is a product of them: A(T) is not a polynomial of degree 3 (the
rotation is trigonometric, the product of three cubics is of degree 9). The board stores and
evaluates A(T) and b(T) element by element as cubics of d = T - t_ref_c, so each of the 12 elements
(a11..a33, b_x, b_y, b_z in g) is fitted by least squares over the model's temperature range (the
range of its steps: the board clamps its temperature to it, so nothing outside is ever applied).

The error of that approximation is reported, not assumed: A and b of the record AS THE BOARD
STORES IT (float32, contracts/sfem_cubic.py `to_f32`) against the model's, on a grid 10x finer than
the fit's, as the largest element errors and as the largest error of the compensated output for a
1 g input in any direction, ||A_rec(T) - A(T)||_2 x 1 g + ||A(T) (b_rec(T) - b(T))||: what the
record adds to the station's own model error anywhere in its range. The verification on the board
(station/daemon/sfem_program.py) counts it in its limit.

Pure: a model in, a record and its error out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contracts.json_safe import JsonDict
from contracts.sfem_cubic import N_COEF, N_POWERS, SfemCubicRecord
from station.science.sfem_model import SfemInsufficientData
from station.science.sfem_thermal import SfemThermalModel

FIT_POINTS = 121  # least-squares nodes over the range (a cubic needs 4; many make it the range's fit)
CHECK_POINTS = 1201  # the error is measured 10x finer than the fit


@dataclass(frozen=True)
class CubicApproximation:
    """How far the record (float32, as stored) is from the station's model over its range."""

    t_lo_c: float
    t_hi_c: float
    max_a_error: float  # largest |A_rec - A| of any element (dimensionless)
    max_b_error_mg: float  # largest |b_rec - b| of any axis, mg
    max_output_error_mg: float  # largest error of the compensated output for a 1 g input (module doc), mg
    worst_temp_c: float  # where max_output_error_mg is reached

    def to_json(self) -> JsonDict:
        return {"t_lo_c": self.t_lo_c, "t_hi_c": self.t_hi_c, "max_a_error": self.max_a_error,
                "max_b_error_mg": self.max_b_error_mg, "max_output_error_mg": self.max_output_error_mg,
                "worst_temp_c": self.worst_temp_c, "check_points": CHECK_POINTS,
                "what": "the record as stored (float32) against the station's model over t_lo..t_hi: "
                        "||dA||_2 x 1 g + ||A db|| (the compensated output's error for a 1 g input)"}


def model_matrices(model: SfemThermalModel, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The station's A(T) (n, 3, 3) and b(T) (n, 3) in g: u_cal = A (u - b) with u the raw reading."""
    p = model.params_at(np.asarray(temp_c, dtype=np.float64))
    return np.asarray(p.A, dtype=np.float64), np.asarray(p.b, dtype=np.float64) * model.acc_g_per_raw


def cubic_record(model: SfemThermalModel) -> tuple[SfemCubicRecord, CubicApproximation]:
    """The version-2 record of a thermal model (module doc) and its measured error. Raises
    SfemInsufficientData when the model spans no temperature range (one step: nothing to clamp to)."""
    t_lo, t_hi = model.temp_range_c
    if not t_hi > t_lo:
        raise SfemInsufficientData(f"the SFEM has one temperature ({t_lo:g} C): a cubic over a range needs two steps")
    t_ref = float(model.t_ref_c)
    temps = np.linspace(t_lo, t_hi, FIT_POINTS)
    a, b = model_matrices(model, temps)
    y = np.concatenate([a.reshape(-1, 9), b], axis=1)  # (n, 12): a11..a33, bx, by, bz
    coef = np.polynomial.polynomial.polyfit(temps - t_ref, y, N_POWERS - 1)  # (4, 12), power 0 first
    assert coef.shape == (N_POWERS, N_COEF)
    rec = SfemCubicRecord(t_ref, t_lo, t_hi, tuple(map(tuple, coef))).to_f32()
    return rec, approximation(rec, model)


def approximation(rec: SfemCubicRecord, model: SfemThermalModel) -> CubicApproximation:
    """The record's error against the model over the record's range (module doc)."""
    temps = np.linspace(rec.t_lo_c, rec.t_hi_c, CHECK_POINTS)
    a, b = model_matrices(model, temps)
    a_rec, b_rec = rec.matrices(temps)
    da, db = a_rec - a, b_rec - b
    out_err = np.linalg.norm(da, ord=2, axis=(1, 2)) + np.linalg.norm(np.einsum("nij,nj->ni", a, db), axis=1)
    k = int(np.argmax(out_err))
    return CubicApproximation(float(rec.t_lo_c), float(rec.t_hi_c), float(np.max(np.abs(da))),
                              float(np.max(np.abs(db)) * 1e3), float(out_err[k] * 1e3), float(temps[k]))


def thermal_model_of(thermal: JsonDict | None) -> SfemThermalModel | None:
    """The station's SfemThermalModel back from its JSON (SfemResult.thermal, sfem_thermal.to_json);
    None when there is none (one temperature step) or it is not of that shape. The station's SFEM
    is fitted on readings in g (results.sfem_result), so one raw unit is one g."""
    if not isinstance(thermal, dict):
        return None
    try:
        coef_doc = thermal["coef"]
        if not isinstance(coef_doc, dict):
            return None
        coef = {name: np.asarray(coef_doc[name], dtype=np.float64) for name in SfemThermalModel.NAMES}
        sig_doc = thermal.get("coef_sigma")
        sig = {name: np.asarray(sig_doc[name], dtype=np.float64) for name in SfemThermalModel.NAMES} \
            if isinstance(sig_doc, dict) and all(n in sig_doc for n in SfemThermalModel.NAMES) else {}
        res_doc = thermal.get("residual_rms")
        resid = {name: np.asarray(res_doc[name], dtype=np.float64) for name in SfemThermalModel.NAMES} \
            if isinstance(res_doc, dict) and all(n in res_doc for n in SfemThermalModel.NAMES) else {}
        temps = np.asarray(thermal["temps_c"], dtype=np.float64)
        degree = int(thermal["degree"])  # type: ignore[call-overload]
        t_ref = float(thermal["t_ref_c"])  # type: ignore[arg-type]
    except (KeyError, TypeError, ValueError):
        return None
    if any(c.shape != (degree + 1, 3) for c in coef.values()) or temps.size == 0:
        return None
    return SfemThermalModel(degree, coef, temps, bool(thermal.get("misalignment_determined", True)), t_ref, resid,
                            [], sig, 1.0)


__all__ = ["CubicApproximation", "cubic_record", "approximation", "model_matrices", "thermal_model_of",
           "FIT_POINTS", "CHECK_POINTS"]
