"""The SFEM part of a calibration certificate, in words (pure: the stored SFEM record in, lines out).

Why a module of its own: the SFEM record (contracts/sfem_result.py) carries more than the
coefficient table holds (which step was judged and why, the thermal model and the sign convention
of its drift, the held-out RMSE, how the fixture's directions were weighed, the model check), and
station/records/certificate.py (the core) and certificate_layout.py (the page) only need its lines
and its coefficients; keeping the reading of the record here keeps both of them short.
Every +- in these lines is 1 sigma; the coefficient table states U = k u (k = 2).
"""

from __future__ import annotations

import math
from typing import Any

from contracts.sfem_result import SfemResult, SfemStepResult
from contracts.types import AXES
from station.decisions.measurements import SFEM_BIAS, SFEM_SCALE_ERROR

MODEL_LINE = ("Model: U_SF = M C S (U - b) (sensors2023 eq. 1). A = M C S maps the raw output, after the bias b "
              "(the raw reading at zero g, in g), to g: S is g per raw unit, so a part whose output per g falls as it "
              "warms has a RISING S; C is the non-orthogonality (lower triangular, small angles), M the misalignment "
              "(a rotation, small angles). Every ± in this section is 1σ.")


def parsed(sfem: Any) -> SfemResult | None:
    """The stored record, or None (no SFEM, or a record of an older shape: the certificate then
    says so instead of guessing)."""
    if not isinstance(sfem, dict):
        return None
    try:
        return SfemResult.from_json(sfem)
    except (ValueError, TypeError):
        return None


def _vec(values: Any, sigmas: Any, k: float, spec: str) -> str:
    vals = values if isinstance(values, (list, tuple)) else [None] * 3
    sigs = sigmas if isinstance(sigmas, (list, tuple)) else [None] * 3
    parts = []
    for ax, v, s in zip(AXES, vals, sigs):
        if v is None:
            parts.append(f"{ax} -")
            continue
        parts.append(f"{ax} {format(v * k, spec)}" + ("" if s is None else f" ± {s * k:.2g}"))
    return ", ".join(parts)


def _step_line(rec: SfemResult, st: SfemStepResult) -> str:
    temps = ", ".join(f"{s.temp_c:.1f}" for s in rec.steps)
    held = "-" if st.rmse_heldout_mg is None else f"{st.rmse_heldout_mg:.3g} mg ({st.detail.get('heldout_method')})"
    return (f"Step judged: {st.temp_c:.1f} °C, the step nearest Tref {rec.t_ref_c:g} °C, of {len(rec.steps)} "
            f"temperature step(s) ({temps} °C); {st.n_positions} positions; |a| - 1 g RMSE before "
            f"{_num(st.rmse_before_mg)} mg, after {_num(st.rmse_after_mg)} mg (in-sample), held-out {held}.")


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3g}"


def _angles_line(st: SfemStepResult) -> str:
    d = st.detail
    non = d.get("nonorthogonality") or {}
    alpha = [non.get("alpha_yx_rad"), non.get("alpha_zx_rad"), non.get("alpha_zy_rad")]
    line = "Non-orthogonality of that step (deg): " + ", ".join(
        f"{n} {math.degrees(v):+.4f}" + ("" if s is None else f" ± {math.degrees(s):.2g}")
        for n, v, s in zip(("yx", "zx", "zy"), alpha, non.get("sigma_rad") or [None] * 3) if v is not None) + "."
    mis = d.get("misalignment") or {}
    if mis.get("determined"):
        line += " Misalignment (rotation vector, deg): " + _vec(mis.get("rotvec_deg"), mis.get("rotvec_sigma_deg"), 1.0,
                                                                 "+.4f") + "."
    else:
        line += " Misalignment: not determined (norm-only fit)."
    return line


def _thermal_line(rec: SfemResult) -> str:
    th = rec.thermal or {}
    drift = rec.drift
    if not th:
        return "Thermal model: none (one temperature step)."
    temps = th.get("temps_c") or []
    line = (f"Thermal model (sensors2023 eq. 8): each parameter a degree-{th.get('degree')} polynomial of "
            f"(T - {rec.t_ref_c:g} °C) over {len(temps)} steps"
            + (f" {min(temps):.1f} to {max(temps):.1f} °C" if temps else "") + ".")
    if drift is not None:
        line += (f" Its drift at {rec.t_ref_c:g} °C in the thermal calibration's convention (martinez2022 eq. 1, the "
                 "drift of the output: TDSF = -(dS/dT)/S, TDB = db/dT - TDSF·b; a part whose output falls as it warms "
                 f"has a negative TDSF): TDSF {_vec(drift.tdsf_ppm_per_c, drift.tdsf_sigma_ppm_per_c, 1.0, '+.1f')} "
                 f"ppm/°C; TDB {_vec(drift.tdb_mg_per_c, drift.tdb_sigma_mg_per_c, 1.0, '+.4f')} mg/°C (σ from the "
                 "steps' fit noise only, not the bias wander over the hours between steps nor the temperature "
                 "reading's error).")
    return line


def _reference_line(st: SfemStepResult) -> str:
    d = st.detail
    if d.get("ref_sigma_deg") is None:
        return "Reference directions: none (norm-only fit)."
    return (f"Reference directions: the fixture's direction error {float(d['ref_sigma_deg']):.2g}° beyond the noise, "
            f"{d.get('ref_sigma_source') or 'assumed'}.")


def sfem_lines(sfem: Any) -> list[str]:
    """The certificate's SFEM section (module doc); [] without an SFEM record."""
    if sfem is None:
        return []
    rec = parsed(sfem)
    if rec is None:
        return ["An SFEM result is stored in a format before the station's SFEM record (sfem-record/1): not "
                "reported here; see the run's stored result."]
    st = rec.reference
    check = rec.model_check()
    return [MODEL_LINE, _step_line(rec, st), _angles_line(st), _thermal_line(rec), _reference_line(st),
            f"Model check (the residual against the part's noise, worst step {float(check['worst_step_temp_c']):.1f} "
            f"°C): {check['words']}. It marks the result; the limits judge the figures (docs/verdicts.md)."]


def sfem_coefficients(sfem: Any) -> list[tuple[str, str, float | None, float | None, str, str, str | None, float]]:
    """(name, axis, value, sigma, unit, note, check measurement, check scale) of the judged step and
    the thermal model's drift: the certificate's coefficient rows (u_combined = the check's sigma
    times check scale, where a check judged it)."""
    rec = parsed(sfem)
    if rec is None:
        return []
    st = rec.reference
    note = f"step {st.temp_c:.1f} °C"
    out: list[tuple[str, str, float | None, float | None, str, str, str | None, float]] = []
    for k, ax in enumerate(AXES):
        b, sb = st.bias_g[k], st.bias_sigma_g[k]
        out.append(("SFEM bias", ax, None if b is None else b * 1e3, None if sb is None else sb * 1e3, "mg", note,
                    SFEM_BIAS.name, 1.0))
    for k, ax in enumerate(AXES):
        s, ss = st.scale[k], st.scale_sigma[k]
        out.append(("SFEM scale - 1", ax, None if s is None else (s - 1.0) * 100.0, None if ss is None else ss * 100.0,
                    "%", note + "; S in g per raw unit", SFEM_SCALE_ERROR.name, 1.0))
    drift = rec.drift
    if drift is not None:
        for k, ax in enumerate(AXES):
            out.append(("SFEM TDSF", ax, drift.tdsf_ppm_per_c[k], drift.tdsf_sigma_ppm_per_c[k], "ppm/°C",
                        "thermal model, martinez2022 sign", None, 1.0))
        for k, ax in enumerate(AXES):
            out.append(("SFEM TDB", ax, drift.tdb_mg_per_c[k], drift.tdb_sigma_mg_per_c[k], "mg/°C",
                        "thermal model, martinez2022 sign", None, 1.0))
    return out


__all__ = ["MODEL_LINE", "sfem_coefficients", "sfem_lines"]
