"""What a run stored, read as Measurements the verdict judges (pure), and what its profile requires.

Every reading makes its Measurements from the declarations (station/decisions/measurements.py):
name, unit, source and where a thermal figure and its 1-sigma sit in the result. A thermal figure
declared with a `section` is read with no code here; the SFEM figures come from
station/decisions/sfem_checks.py, the link counters, the programming record and the verification
have their few lines each below.

What a profile itself requires, whatever the product's limits (design 8), is declared on each
measurement too (`required_by`): a thermal or SFEM analysis its figures and the lost samples; a
verified profile its contract checks, fixed limits a site cannot configure away (readback CRC,
compensation on, no axis failing the verification), and the verified drift error.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import SupportsInt

from contracts.types import AXES
from station.decisions.limits import Limit
from station.decisions.measurements import (COMPENSATION_ON, FIT_AGREEMENT_TDB, FIT_AGREEMENT_TDSF, LINK_ERRORS,
                                            LOST_SAMPLES, PROGRAM_CRC_MATCH, TDB, TDSF, VERIFIED_DRIFT_ERROR_FS,
                                            VERIFY_FAILED_AXES, Measurement, MeasurementDef, Requirer, as_float,
                                            finite, in_section, required_by)
from station.decisions.sfem_checks import sfem_figures

Record = Mapping[str, object]
_EMPTY: Record = {}


def _sub(record: Record | None, key: str) -> Record:
    """record[key] when it is a (non-empty) record, else an empty one (a missing part reads as none)."""
    v = record.get(key) if record else None
    return v if isinstance(v, Mapping) and v else _EMPTY


def _count(v: object) -> int:
    """A stored counter as an int (missing: 0)."""
    if not v:
        return 0
    if isinstance(v, (str, bytes, SupportsInt)):
        return int(v)
    raise TypeError(f"a counter, not {type(v).__name__}")


def thermal_measurements(result: Record | None) -> list[Measurement]:
    """From a thermal result (the `station calibrate --json` shape plus its "residual" report): per
    axis the offline fit's figures (section "axes"), |streaming - offline| of TDB and TDSF, and the
    residual report's figures (section "residual")."""
    if not result:
        return []
    out: list[Measurement] = []
    offline, streaming, residual = _sub(result, "axes"), _sub(_sub(result, "streaming"), "axes"), \
        _sub(_sub(result, "residual"), "axes")
    for ax in AXES:
        a = _sub(offline, ax)
        if a:
            out += [d.read(a, ax) for d in in_section("axes")]
        s = _sub(streaming, ax)
        for agreement, of in ((FIT_AGREEMENT_TDB, TDB), (FIT_AGREEMENT_TDSF, TDSF)):
            off, fast = as_float(a.get(of.name)), as_float(s.get(of.name))
            if off is not None and fast is not None:
                out.append(agreement.measured(abs(fast - off), ax))
        r = _sub(residual, ax)
        if r:
            out += [d.read(r, ax) for d in in_section("residual")]
    return out


def sfem_measurements(result: Record | None) -> list[Measurement]:
    """The SFEM figures the verdict judges (station/decisions/sfem_checks.py): bias and scale of
    the step nearest t_ref_c with their 1-sigma, its held-out RMSE, the model check's residual ratio."""
    return sfem_figures(result)


def link_measurements(link_stats: Record | None, n_samples: int) -> list[Measurement]:
    """Lost samples (% of expected) and link errors (bad/malformed frames, board error replies)."""
    st = link_stats or _EMPTY
    # what the station lost while it ran behind this link is its own backlog, not the part's
    # (station/daemon/intake_monitor.py): the lost-sample figure judges what the link lost
    lost_all = _count(st.get("samples_lost", 0))
    lost = max(0, lost_all - _count(st.get("samples_lost_station", 0)))
    total = int(n_samples) + lost_all
    out = [LINK_ERRORS.measured(sum(_count(st.get(k, 0)) for k in ("frames_bad_checksum", "frames_malformed",
                                                                     "errors_reported")))]
    if total > 0:
        out.append(LOST_SAMPLES.measured(100.0 * lost / total))
    return out


def program_measurements(program: Record | None) -> list[Measurement]:
    """Program-and-verify, part 1, as measurements: the readback CRC equal to the written one (1/0)
    and on-board compensation confirmed on (1/0). No record (never programmed, e.g. the write
    faulted the slot or a resume skipped the program step) -> nothing: the requirement reports it."""
    if not program or not program.get("programmed"):
        return []
    crc, rb = program.get("crc"), program.get("readback_crc")
    match = bool(crc) and crc == rb and program.get("readback_identical") is not False
    return [PROGRAM_CRC_MATCH.measured(1.0 if match else 0.0, source=f"written {crc}, read back {rb}"),
            COMPENSATION_ON.measured(1.0 if program.get("comp") else 0.0)]


def verification_measurements(verification: Record | None) -> list[Measurement]:
    """Program-and-verify, part 2: the verified drift error E_FS of the compensated output per axis
    (with its 1-sigma) and how many axes fail the verification's rules (ratio, curvature, rise)."""
    if not verification:
        return []
    e_fs, e_sig = _sub(verification, "e_after_fs_pct"), _sub(verification, "e_after_fs_sigma_pct")
    out = [VERIFIED_DRIFT_ERROR_FS.measured(e_fs.get(ax), ax, e_sig.get(ax)) for ax in AXES if finite(e_fs.get(ax))]
    axes = _sub(verification, "axes")
    if axes:
        failed = sum(1 for a in AXES if not _sub(axes, a).get("passed", False))
        out.append(VERIFY_FAILED_AXES.measured(float(failed)))
    return out


# ---- what a profile requires ---------------------------------------------------------------------
_ANALYSES: dict[str, Requirer] = {"thermal": "thermal", "sfem": "sfem"}  # the analyses that require figures


def contract_limit(d: MeasurementDef) -> Limit:
    """The fixed limit of a contract measurement (a verified profile's readback CRC, ...)."""
    low, high = d.contract or (None, None)
    return Limit(measurement=d.name, low=low, high=high, unit=d.unit, label=d.label, required=True, analysis="any")


def profile_requirements(analysis: str, program_verify: bool) -> tuple[Limit | str, ...]:
    """Measurements (names, or fixed contract limits) a run of this profile must have to pass, in
    declaration order: its analysis's (thermal, sfem; none for any other), then program and verify's
    (an SFEM profile's: the readback CRC, compensation on and no axis failing the verification on the
    board; its figure is the residual against the station's model, not a thermal drift error E)."""
    by = _ANALYSES.get(analysis)
    names: tuple[Limit | str, ...] = tuple(d.name for d in required_by(by)) if by is not None else ()
    if not program_verify:
        return names
    pv: Requirer = "sfem_program" if analysis == "sfem" else "program_verify"
    return names + tuple(contract_limit(d) if d.contract else d.name for d in required_by(pv))


@dataclass(frozen=True)
class RunRecord:
    """Everything a run stored that its verdict stands on, as plain data (from a live DutRun, a
    resumed one or the database alike)."""

    analysis: str  # the profile's analysis: thermal, sfem, none
    program_verify: bool  # the profile ends with program and verify
    end_state: str  # done, faulted, interrupted, aborted, ... (anything but done is error)
    end_reason: str = ""
    result: Record | None = None  # thermal or SFEM result
    link_stats: Record | None = None
    n_samples: int = 0
    program: Record | None = None
    verification: Record | None = None
    # the board's own calibrator against the station's result (contracts/selfcal_opinion.py, its JSON):
    # None when the profile's option board_selfcal is off
    board_selfcal: Record | None = None


def run_measurements(run: RunRecord) -> list[Measurement]:
    """Everything the run measured that a verdict may judge."""
    ms: list[Measurement] = []
    if run.analysis == "thermal":
        ms += thermal_measurements(run.result)
    elif run.analysis == "sfem":
        ms += sfem_measurements(run.result)
    ms += link_measurements(run.link_stats, run.n_samples)
    if run.program_verify:
        ms += program_measurements(run.program) + verification_measurements(run.verification)
    return ms


__all__ = ["Record", "RunRecord", "thermal_measurements", "sfem_measurements", "link_measurements",
           "program_measurements", "verification_measurements", "run_measurements", "profile_requirements",
           "contract_limit"]
