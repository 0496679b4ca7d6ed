"""What the verdict reads from an SFEM result (pure: the stored record in, plain figures out).

Why a module of its own: the SFEM record has its own typed shape (contracts/sfem_result.py), its
own choice of step and its own model check; the verdict (readings.py, checks.py) takes its
Measurements (declared in measurements.py) and its mark without knowing the record's layout.

Which step is judged: the step nearest the record's t_ref_c (25 C, or the profile's
sfem_reference_temp_c): the temperature the product's SFEM limits are written for, whichever
order the profile ran its steps in (SfemResult.reference_index). A record of any other shape
gives no figures, so the profile's required SFEM measurements are "not measured" (error), never
a pass on a half-read result.

The model check (`sfem_fit_mark`): the worst step's residual against its noise, in the words of
station/science/sfem_goodness.py ("residual 9.8 x the noise: the model misses an effect; a g^2
nonlinearity of about ... explains it"). It MARKS the verdict, it does not decide it: the ratio is
relative to the part's noise, so a quiet part whose missing effect is far inside any accuracy spec
reads as high as a noisy one with a large effect (sfem_goodness module doc); the sigmas the limits
are judged with are already scaled by it. A product that wants to hold or fail on it limits the
measurement `sfem_residual_ratio` (or, better, the size: `sfem_heldout_rmse_mg`, in mg), and then
its own limit judges it instead of the mark.
"""

from __future__ import annotations

from collections.abc import Mapping

from contracts.json_safe import finite_or_none
from contracts.sfem_result import SfemResult
from contracts.types import AXES
from station.decisions.measurements import (SFEM_BIAS, SFEM_HELDOUT_RMSE, SFEM_RESIDUAL_RATIO, SFEM_SCALE_ERROR,
                                            Measurement)

RESIDUAL_RATIO = SFEM_RESIDUAL_RATIO.name
RESIDUAL_RATIO_UNIT = SFEM_RESIDUAL_RATIO.unit


def parsed(result: Mapping[str, object] | None) -> SfemResult | None:
    """The record, or None when there is none or it has another shape (module doc)."""
    if not result:
        return None
    try:
        return SfemResult.from_json(result)
    except (ValueError, TypeError):
        return None


def sfem_figures(result: Mapping[str, object] | None) -> list[Measurement]:
    """The judged step's figures (nearest t_ref_c): bias (mg) and |scale - 1| (%) per axis with
    their 1-sigma, the step's held-out |a| - 1 g RMSE (mg), and the worst step's residual ratio
    (the model check's number); declared in station/decisions/measurements.py."""
    rec = parsed(result)
    if rec is None:
        return []
    st = rec.reference
    src = f"sfem step {st.temp_c:.1f} C (nearest {rec.t_ref_c:g} C)"
    out: list[Measurement] = []
    for k, ax in enumerate(AXES):
        b, sb = st.bias_g[k], st.bias_sigma_g[k]
        if b is not None:
            out.append(SFEM_BIAS.measured(b * 1e3, ax, None if sb is None else sb * 1e3, src))
        sc, ss = st.scale[k], st.scale_sigma[k]
        if sc is not None:
            out.append(SFEM_SCALE_ERROR.measured(abs(sc - 1.0) * 100.0, ax, None if ss is None else ss * 100.0, src))
    if st.rmse_heldout_mg is not None:
        out.append(SFEM_HELDOUT_RMSE.measured(st.rmse_heldout_mg, None, None, src))
    worst = rec.worst
    if worst.residual_ratio is not None:
        out.append(SFEM_RESIDUAL_RATIO.measured(worst.residual_ratio, None, None, f"sfem step {worst.temp_c:.1f} C"))
    return out


def sfem_fit_mark(result: Mapping[str, object] | None) -> tuple[float | None, str] | None:
    """(worst residual ratio, its words) for the verdict's mark (module doc); None without a record."""
    rec = parsed(result)
    if rec is None:
        return None
    check = rec.model_check()
    ratio = finite_or_none(check.get("worst_residual_ratio"))
    words = str(check.get("words") or "")
    where = f"SFEM model check (step {float(check['worst_step_temp_c']):.1f} C): " if check.get("worst_step_temp_c") \
        is not None else "SFEM model check: "
    return ratio, where + words


__all__ = ["RESIDUAL_RATIO", "RESIDUAL_RATIO_UNIT", "parsed", "sfem_figures", "sfem_fit_mark"]
