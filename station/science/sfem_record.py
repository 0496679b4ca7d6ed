"""SFEM of a whole record: THE pipeline of the station's SFEM, for the daemon and the command line.

Why a module of its own: this is the one function both the station's analysis
(station/daemon/results.py sfem_result, on a run's samples) and `station sfem` (on a log, e.g. a
run exported from the database) call, so the two give the same numbers from the same samples. It
only composes the other SFEM modules:

    placed rows -> sfem_positions (static positions per temperature step) -> per step: sfem (fit),
    sfem_goodness (the residual against the noise, the fixture's measured direction error, the fit
    redone with both), sfem_heldout (held-out RMSE) -> sfem_thermal (cubic polynomials of T)

Which samples: a record with a `position` column is fitted on its placed samples only (design 4,
"Where the plate is": -1 rows are the plate being turned, not yet settled, or somewhere else), the
labels kept where the samples show the labelled position settled (placement.settled_labels, as
`station calibrate` does), and the reference direction of a placed sample is its position's
nominal gravity (contracts.positions) when the record has no ref_x/y/z columns. The steps' windows
are the static intervals the detector finds in those samples (static_detect, with the soak
discipline of sfem_positions): the same whether the samples come from a live run or its log.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from contracts.positions import GRAVITY_DIRECTIONS
from contracts.sfem_result import SfemResult, SfemStepResult
from contracts.types import T_REF_C
from station.science.chunked import keep_rows
from station.science.placement import settled_labels
from station.science.sfem import DEFAULT_REF_SIGMA_DEG, MIN_POSITIONS_NORM_ONLY, MIN_POSITIONS_REFERENCE, fit_sfem
from station.science.sfem_goodness import goodness_of_fit, reference_scatter_deg
from station.science.sfem_heldout import heldout_rmse
from station.science.sfem_model import SfemFit, SfemInsufficientData
from station.science.sfem_positions import PositionSet, group_static_positions
from station.science.sfem_thermal import SfemThermalModel
from station.science.static_detect import StaticDetectConfig


@dataclass
class SfemRecordResult:
    """SFEM of a record: one fit per temperature step (coldest first) and, with >= 2 steps, the
    polynomial thermal model. `main` is the step nearest t_ref_c (the headline figures, the verdict)."""

    fits: list[SfemFit]
    main: SfemFit
    thermal: SfemThermalModel | None
    n_static_intervals: int
    skipped_steps: list[dict]
    notes: list[str]
    t_ref_c: float = T_REF_C

    def to_result(self) -> SfemResult:
        """The typed record that is stored, served and judged (contracts/sfem_result.py)."""
        steps = tuple(SfemStepResult.from_json(f.to_json(), i) for i, f in enumerate(self.fits))
        return SfemResult(steps, self.t_ref_c, None if self.thermal is None else self.thermal.to_json(),
                          self.n_static_intervals, tuple(self.skipped_steps), tuple(self.notes))

    def to_json(self) -> dict:
        return self.to_result().to_json()


def placed_rows(
    time_s: np.ndarray | None, acc: np.ndarray, temp_c: np.ndarray | None, ref_dir: np.ndarray | None,
    position: np.ndarray | None, acc_g_per_raw: float = 1.0, in_place: bool = False,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The rows the SFEM fits (module doc): placed samples only when the record says where it was
    placed, with reference directions from the positions when it has none of its own.
    in_place: the placed rows are moved to the front of the given arrays (float64, int64 for the
    position), which are returned cut to them: no copy of a long log (the arrays are spent)."""
    a = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    if position is None:
        return time_s, a, temp_c, ref_dir, None
    pos = np.asarray(position).reshape(-1).astype(np.int64, copy=not in_place)
    if not (pos >= 0).any():
        return time_s, a, temp_c, ref_dir, pos
    if time_s is not None:
        settled_labels(np.asarray(time_s, dtype=np.float64), a if acc_g_per_raw == 1.0 else a * acc_g_per_raw, pos,
                       out=pos)  # the labels over the column (ours: a copy unless in_place): one array, not two
    keep = pos >= 0
    if in_place:
        cols = [x for x in (time_s, temp_c, ref_dir) if x is not None]
        kept = keep_rows(keep, a, pos, *[np.asarray(x, dtype=np.float64) for x in cols])
        a, pos, rest = kept[0], kept[1], iter(kept[2:])
        t = None if time_s is None else next(rest)
        tc = None if temp_c is None else next(rest)
        given_ref = None if ref_dir is None else next(rest).reshape(-1, 3)
    else:
        t = None if time_s is None else np.asarray(time_s, dtype=np.float64)[keep]
        tc = None if temp_c is None else np.asarray(temp_c, dtype=np.float64)[keep]
        given_ref = None if ref_dir is None else np.asarray(ref_dir, dtype=np.float64).reshape(-1, 3)[keep]
        a, pos = a[keep], pos[keep]
    if given_ref is not None:
        ref = given_ref
    elif pos.size and (pos < len(GRAVITY_DIRECTIONS)).all():
        ref = GRAVITY_DIRECTIONS[pos]
    else:
        ref = None
    return t, a, tc, ref, pos


def fit_step(ps: PositionSet, acc: np.ndarray, norm_only: bool, ref_sigma_deg: float | None,
             acc_g_per_raw: float = 1.0) -> SfemFit:
    """One temperature step (station/science/sfem_goodness.py module doc): a first fit with the
    configured reference sigma (else the default), its residual against the noise, then the fit
    again with every position's noise scaled by that ratio (when above 1) and the reference sigma
    the step's own direction residuals measure (>= 9 positions), its goodness and held-out RMSE."""
    prior = DEFAULT_REF_SIGMA_DEG if ref_sigma_deg is None else float(ref_sigma_deg)
    prior_words = "the profile's sfem_ref_sigma_deg" if ref_sigma_deg is not None else "the documented default"
    refs = None if norm_only else ps.ref_dir
    kw = dict(raw_per_g=1.0 / acc_g_per_raw, temp_c=ps.step_temp_c, positions=ps.position, n_samples=ps.n_samples)
    first = fit_sfem(ps.mean, refs, noise_g=ps.noise_g, ref_sigma_deg=prior, **kw)
    gof = goodness_of_fit(first, ps.mean)
    noise = ps.noise_g * max(1.0, gof.residual_ratio or 1.0)
    used, source = prior, f"{prior_words} ({prior:g} deg): too few positions to measure it"
    if not norm_only:
        measured, dof = reference_scatter_deg(first, noise)
        if measured is not None:
            used = measured
            source = (f"measured on this step's direction residuals ({dof} degrees of freedom; "
                      f"{prior_words} would be {prior:g} deg)")
    fit = fit_sfem(ps.mean, refs, noise_g=noise, ref_sigma_deg=used, **kw)
    # ref_sigma_source says how the directions were weighed; fit_sfem's "(assumed ...)" note would repeat it
    fit.notes = [n for n in fit.notes if not n.startswith("reference direction residual")]
    fit.goodness = gof
    fit.ref_sigma_source = "" if norm_only else source
    fit.rmse_heldout_mg, fit.heldout_method = heldout_rmse(
        np.asarray(acc, dtype=np.float64), replace(ps, noise_g=noise), norm_only, used, acc_g_per_raw)
    return fit


def fit_sfem_record(
    time_s: np.ndarray | None,
    acc: np.ndarray,
    temp_c: np.ndarray | None = None,
    ref_dir: np.ndarray | None = None,
    position: np.ndarray | None = None,
    *,
    norm_only: bool = False,
    ref_sigma_deg: float | None = None,
    config: StaticDetectConfig | None = None,
    acc_g_per_raw: float = 1.0,
    temp_gap_c: float = 3.0,
    t_ref_c: float = T_REF_C,
    consume: bool = False,
) -> SfemRecordResult:
    """Placed rows -> static positions per temperature step -> fit_step per step -> cubic model.

    norm_only ignores ref_dir; otherwise reference directions are required (ref_dir, or a position
    column). ref_sigma_deg: the fixture's direction error where a step cannot measure it (None: the
    documented default). Steps with too few positions are skipped (listed in skipped_steps); no
    usable step raises SfemInsufficientData. consume: the given arrays may be overwritten (their
    placed rows moved to the front, placed_rows in_place): `station sfem` reads a log for this call
    alone, and a long log then costs no second copy of its placed rows.
    """
    time_s, acc, temp_c, ref_dir, position = placed_rows(time_s, acc, temp_c, ref_dir, position, acc_g_per_raw,
                                                         in_place=consume)
    if not norm_only and ref_dir is None:
        raise SfemInsufficientData("no reference directions (ref_x, ref_y, ref_z, or a position column): give them "
                                   "or use a norm-only fit")
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
        fits.append(fit_step(ps, acc, norm_only, ref_sigma_deg, acc_g_per_raw))
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
        thermal = SfemThermalModel.fit([(f.temp_c, f) for f in fits], t_ref_c=t_ref_c, acc_g_per_raw=acc_g_per_raw)
        notes.extend(thermal.notes)
    main = min(fits, key=lambda f: abs(f.temp_c - t_ref_c))
    return SfemRecordResult(fits, main, thermal, n_intervals, skipped, notes, t_ref_c)


__all__ = [
    "SfemRecordResult",
    "fit_sfem_record",
    "fit_step",
    "placed_rows",
]
