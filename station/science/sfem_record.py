"""SFEM of a whole record: static positions per temperature step, one fit per step, thermal polynomials.

Why a module of its own: this is the pipeline the `station sfem` command and the acceptance tests
run on a log, and it only composes the other SFEM modules (sfem_positions -> sfem -> sfem_heldout
-> sfem_thermal); keeping it on top means none of them depends on the whole pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.science.sfem import DEFAULT_REF_SIGMA_DEG, MIN_POSITIONS_NORM_ONLY, MIN_POSITIONS_REFERENCE, fit_sfem
from station.science.sfem_heldout import heldout_rmse
from station.science.sfem_model import SfemFit, SfemInsufficientData
from station.science.sfem_positions import group_static_positions
from station.science.sfem_thermal import SfemThermalModel
from station.science.static_detect import StaticDetectConfig
from contracts.types import T_REF_C


@dataclass
class SfemRecordResult:
    """SFEM of a record: one fit per temperature step (coldest first) and, with >= 2 steps, the
    polynomial thermal model. `main` is the step nearest t_ref_c (the headline figures)."""

    fits: list[SfemFit]
    main: SfemFit
    thermal: SfemThermalModel | None
    n_static_intervals: int
    skipped_steps: list[dict]
    notes: list[str]

    def to_json(self) -> dict:
        out = self.main.to_json()
        out["n_static_intervals"] = self.n_static_intervals
        out["temperature_steps_c"] = [f.temp_c for f in self.fits]
        out["steps"] = [f.to_json() for f in self.fits]
        out["thermal"] = None if self.thermal is None else self.thermal.to_json()
        out["skipped_steps"] = self.skipped_steps
        out["notes"] = list(dict.fromkeys(out["notes"] + self.notes))
        return out


def fit_sfem_record(
    time_s: np.ndarray | None,
    acc: np.ndarray,
    temp_c: np.ndarray | None = None,
    ref_dir: np.ndarray | None = None,
    position: np.ndarray | None = None,
    *,
    norm_only: bool = False,
    ref_sigma_deg: float = DEFAULT_REF_SIGMA_DEG,
    config: StaticDetectConfig | None = None,
    acc_g_per_raw: float = 1.0,
    temp_gap_c: float = 3.0,
    t_ref_c: float = T_REF_C,
) -> SfemRecordResult:
    """Static intervals -> positions per temperature step -> fit_sfem per step -> cubic model.

    norm_only ignores ref_dir; otherwise ref_dir is required. Steps with too few positions are
    skipped (listed in skipped_steps); no usable step raises SfemInsufficientData.
    """
    if not norm_only and ref_dir is None:
        raise SfemInsufficientData("no reference directions (ref_x, ref_y, ref_z): give them or use a norm-only fit")
    need = MIN_POSITIONS_NORM_ONLY if norm_only else MIN_POSITIONS_REFERENCE
    cfg = config or StaticDetectConfig()
    sets = group_static_positions(
        time_s, acc, temp_c, None if norm_only else ref_dir, position,
        config=cfg, acc_g_per_raw=acc_g_per_raw, temp_gap_c=temp_gap_c,
    )  # fmt: skip
    n_intervals = sum(len(spans) for ps in sets for spans in ps.spans)
    fits, skipped = [], []
    for ps in sets:
        if len(ps) < need:
            skipped.append({"temp_c": ps.step_temp_c, "n_positions": len(ps), "reason": f"fewer than {need} positions"})
            continue
        fit = fit_sfem(
            ps.mean,
            None if norm_only else ps.ref_dir,
            noise_g=ps.noise_g,
            ref_sigma_deg=ref_sigma_deg,
            raw_per_g=1.0 / acc_g_per_raw,
            temp_c=ps.step_temp_c,
            positions=ps.position,
            n_samples=ps.n_samples,
        )
        fit.rmse_heldout_mg, fit.heldout_method = heldout_rmse(
            np.asarray(acc, dtype=np.float64), ps, norm_only, ref_sigma_deg, acc_g_per_raw)
        fits.append(fit)
    if not fits:
        best = max((len(ps) for ps in sets), default=0)
        kind = "norm-only fit" if norm_only else "reference fit"
        raise SfemInsufficientData(
            f"too few static positions: found {best} in the best temperature step (need at least {need} for a {kind})"
        )
    notes = []
    if skipped:
        notes.append(f"{len(skipped)} temperature step(s) skipped: too few static positions")
    thermal = None
    if len(fits) >= 2:
        thermal = SfemThermalModel.fit([(f.temp_c, f) for f in fits], t_ref_c=t_ref_c)
        notes.extend(thermal.notes)
    main = min(fits, key=lambda f: abs(f.temp_c - t_ref_c))
    return SfemRecordResult(fits, main, thermal, n_intervals, skipped, notes)


__all__ = [
    "SfemRecordResult",
    "fit_sfem_record",
]
