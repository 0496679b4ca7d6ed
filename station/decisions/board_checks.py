"""What the verdict reads from the issue-42 board records (pure: stored JSON in, findings out).

Two records, each judged by one check of station/decisions/checks.py:

- the board's own calibrator against the station's result (contracts/selfcal_opinion.py, the
  profile option `board_selfcal`): the check `board_selfcal_agrees`. Applicable (the board has a
  calibrator): one flag that DECIDES (pass: every figure agrees within K x their combined
  uncertainty; fail: a figure does not, named with both values; error: a capable board whose
  result was not read or not comparable, never a pass) and, shown beside it, every figure side by
  side per axis (`board_selfcal_tdb_mg_per_c`, `board_selfcal_tdsf_ppm_per_c`: the board's value,
  its 1-sigma, the station's window station +- K u). Not applicable (no calibrator on the board):
  a mark with the words, never a fail.
- the cubic SFEM verified on the board (station/daemon/sfem_program.py): per axis the residual
  rms and max of the board's compensated output against the station's model, with the run's own
  limits. They mark the verdict (words, the failing ones among the reasons); what decides is the
  contract measurement `verify_failed_axes`, as for a thermal verification.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from contracts.json_safe import finite_or_none
from contracts.selfcal_opinion import SelfCalOpinion
from contracts.types import AXES
from station.decisions.judging import Check, fmt
from station.decisions.measurements import (SFEM_VERIFIED_RESIDUAL_MAX, SFEM_VERIFIED_RESIDUAL_RMS, MeasurementDef,
                                            declare)
from station.science.selfcal_compare import opinion_words, row_words

BOARD_SELFCAL_AGREES = declare(MeasurementDef(
    "board_selfcal_agrees", "", "board's own calibrator agrees with the station", "board calibrator agrees", False,
    "flag", "", "board selfcal"))
BOARD_SELFCAL_TDB = declare(MeasurementDef(
    "board_selfcal_tdb_mg_per_c", "mg/C", "board's own TDB", "board calibrator TDB", True, "signed",
    "station/science/selfcal_compare.py: the board's end-of-test computation on its G segments under the part's "
    "noise (white, bias wander, temperature quantiser)", "board selfcal"))
BOARD_SELFCAL_TDSF = declare(MeasurementDef(
    "board_selfcal_tdsf_ppm_per_c", "ppm/C", "board's own TDSF", "board calibrator TDSF", True, "signed",
    BOARD_SELFCAL_TDB.sigma, "board selfcal"))
SFEM_CUBIC_KIND = "sfem-cubic"  # the verification record's kind (station/daemon/sfem_program.py)


@dataclass(frozen=True)
class Finding:
    """One check, and whether it decides (False: a mark, `tell`: its words among the reasons)."""

    check: Check
    decides: bool
    tell: bool = False


def selfcal_findings(opinion: Mapping[str, object] | None) -> list[Finding]:
    """The check `board_selfcal_agrees` on a run's opinion (module doc); [] without one (option off)."""
    if opinion is None:
        return []
    name = BOARD_SELFCAL_AGREES.name
    try:
        op = SelfCalOpinion.from_json(dict(opinion))
    except ValueError as exc:
        return [Finding(Check(name, None, None, None, "", 1.0, 1.0, "error", f"board's own calibrator: {exc}"), True)]
    words = opinion_words(op)
    if not op.applicable:
        return [Finding(Check(name, None, None, None, "", None, None, "pass", words), False)]
    if op.error is not None or not op.rows:
        return [Finding(Check(name, None, None, None, "", 1.0, 1.0, "error", words), True)]
    out = [Finding(Check(name, None, 1.0 if op.agrees else 0.0, None, "", 1.0, 1.0,
                         "pass" if op.agrees else "fail", words), True)]
    for r in op.rows:
        d = BOARD_SELFCAL_TDB if r.figure == "tdb_mg_per_c" else BOARD_SELFCAL_TDSF
        half = r.k * r.u_combined
        out.append(Finding(Check(d.name, r.axis, r.board, r.u_board, d.unit, r.station - half, r.station + half,
                                 "pass" if r.agrees else "fail", row_words(r)), False))
    return out


def sfem_verify_findings(verification: Mapping[str, object] | None) -> list[Finding]:
    """The cubic SFEM verified on the board, per axis (module doc); [] for any other verification."""
    if not verification or verification.get("kind") != SFEM_CUBIC_KIND:
        return []
    axes = verification.get("axes")
    if not isinstance(axes, Mapping):
        return []
    out: list[Finding] = []
    for ax in AXES:
        a = axes.get(ax)
        if not isinstance(a, Mapping):
            continue
        sigma = finite_or_none(a.get("sigma_mg"))
        span = verification.get("temp_range_c")
        over = f" over {fmt(finite_or_none(span[0]))}..{fmt(finite_or_none(span[1]))} C" \
            if isinstance(span, (list, tuple)) and len(span) == 2 else ""
        for d, key, lim_key in ((SFEM_VERIFIED_RESIDUAL_RMS, "residual_rms_mg", "limit_rms_mg"),
                                (SFEM_VERIFIED_RESIDUAL_MAX, "residual_max_mg", "limit_max_mg")):
            v, lim = finite_or_none(a.get(key)), finite_or_none(a.get(lim_key))
            ok = v is not None and lim is not None and v <= lim
            what = "rms" if key == "residual_rms_mg" else "max"
            words = (f"{ax} SFEM on the board: residual {what} {fmt(v)} mg{over} "
                     f"{'within' if ok else 'over'} its limit {fmt(lim)} mg (from the fit's own figures, "
                     f"sigma {fmt(sigma)} mg)")
            out.append(Finding(Check(d.name, ax, v, sigma, d.unit, None, lim, "pass" if ok else "fail", words),
                               False, tell=not ok))
    return out


__all__ = ["BOARD_SELFCAL_AGREES", "BOARD_SELFCAL_TDB", "BOARD_SELFCAL_TDSF", "SFEM_CUBIC_KIND", "Finding",
           "selfcal_findings", "sfem_verify_findings"]
