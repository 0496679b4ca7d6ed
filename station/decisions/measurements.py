"""Every measurement the verdict judges, declared once: name, unit, axes, how its 1-sigma is found,
what a limit on it means and the words the operator and the records read.

A `MeasurementDef` is the one place a measurement is written down (OpenHTF-style). Everything else
reads it: the readings (station/decisions/readings.py: which result field holds the value and its
1-sigma), the profile's requirements (`required_by`, and the contract limits of a verified profile),
the built-in limits (station/decisions/limits.py: unit, label and the analysis a limit applies to),
the verdict's words ("z TDSF -612 ppm/C, limit -500": label and unit), and the records (the SPC and
Pareto words, station/records/parameter_names.py; the certificate's flags and coefficient names; the
exports' stable test numbers, `test_number`).
A new measurement is one `declare(MeasurementDef(...))`; a check that computes one declares it with
itself (station/decisions/checks.py `VerdictCheck.declares`).

`Measurement` is one measured number of one run: what a reading makes of a declaration.

The order of declaration is the order of the profile's requirements (the verdict lists a missing
one in that order): the thermal figures, the SFEM figures, the link counters, program and verify.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal

from contracts.types import AXES

# What a limit on a measurement means (docs/verdicts.md "Limits as data"):
#   signed  a signed value: a limit is low and/or high (one- or two-sided: TDB -1.5..1.5, TDSF >= -500)
#   size    >= 0 by construction (|x|, an RMS, an error E, a percentage): an upper limit, |x| <= high
#   ratio   a dimensionless ratio >= 0 (a residual over what the noise predicts): an upper limit
#   count   whole counts >= 0 (frames, axes): an upper limit (0: none allowed)
#   flag    1 = yes, 0 = no: a limit low = high = 1
Kind = Literal["signed", "size", "ratio", "count", "flag"]
KINDS: tuple[Kind, ...] = ("signed", "size", "ratio", "count", "flag")
# Where a reading finds a thermal figure in the result (station/decisions/readings.py):
#   axes      the offline fit's per-axis record, result["axes"][axis]
#   residual  the residual-drift report, result["residual"]["axes"][axis]
#   ""        computed or read by its own code (SFEM, link, program and verify, a check's own)
Section = Literal["axes", "residual", ""]
# Which part of a profile requires a measurement whatever the product's limits (design 8):
# program_verify a thermal profile's, sfem_program an SFEM profile's program and verify (issue 42:
# the cubic SFEM on the board, verified against the station's model on a cool-down)
Requirer = Literal["thermal", "sfem", "program_verify", "sfem_program"]
LimitAnalysis = Literal["thermal", "sfem", "any"]

# The unit strings of the checks are ASCII for logs and CSV; a person reads °C, µg and √Hz.
UNIT_WORDS: dict[str, str] = {"mg/C": "mg/°C", "ppm/C": "ppm/°C", "ug/sqrt(Hz)": "µg/√Hz", "ug": "µg"}
FLAG_UNIT_WORDS = "1 = yes"


def finite(v: object) -> bool:
    """A real number that is finite (numpy scalars included; a bool is no measurement)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(float(v))


def as_float(v: object) -> float | None:
    """`v` as a float when it is a finite real number (finite), else None."""
    return float(v) if finite(v) and isinstance(v, numbers.Real) else None


def readable_unit(unit: str) -> str:
    """A check's ASCII unit as a person reads it ('mg/C' -> 'mg/°C')."""
    return UNIT_WORDS.get(unit, unit)


@dataclass(frozen=True)
class Measurement:
    """One measured number: value and 1-sigma uncertainty (None = not known) in `unit`."""

    name: str
    value: float | None
    unit: str = ""
    axis: str | None = None
    sigma: float | None = None
    source: str = ""


@dataclass(frozen=True)
class MeasurementDef:
    """One measurement, declared once (module doc)."""

    name: str  # units in the name: tdb_mg_per_c
    unit: str  # as the checks carry it (ASCII): mg/C
    label: str  # the operator's words in a reason: "TDSF" -> "z TDSF -612 ppm/C, limit -500"
    title: str  # the records' words (SPC, Pareto): "drift error E_FS"
    per_axis: bool  # one value per axis x, y, z; else one per run
    kind: Kind  # what a limit on it means (KINDS above)
    sigma: str  # how its 1-sigma is found ("" = it has none: judged on its value and the limit's u_sys)
    source: str = ""  # where the value comes from (Measurement.source; a reading may say more)
    analysis: LimitAnalysis = "thermal"  # the analysis a built-in limit on it applies to
    section: Section = ""  # where a thermal reading finds it (Section above): value result[...][name]
    sigma_key: str = ""  # the result field next to the value that holds its 1-sigma
    required_by: tuple[Requirer, ...] = ()  # required by these profiles whatever the product's limits
    contract: tuple[float | None, float | None] | None = None  # (low, high) a site cannot take away
    test_number: int | None = None  # stable STDF/OCPTV test number (+ 1/2/3 for axis x/y/z); None: hashed

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z][a-z0-9_]*", self.name) or len(self.name) > 64:
            raise ValueError(f"measurement name {self.name!r}: lower-case letters, digits and _, at most 64")
        if self.kind not in KINDS:
            raise ValueError(f"measurement {self.name!r}: kind {self.kind!r} is none of {', '.join(KINDS)}")
        if self.contract is not None and not self.required_by:
            raise ValueError(f"measurement {self.name!r}: a contract limit needs a profile that requires it")
        if self.sigma_key and not self.section:
            raise ValueError(f"measurement {self.name!r}: sigma_key {self.sigma_key!r} without a section")

    @property
    def axes(self) -> tuple[str, ...]:
        """The axes it comes per (empty: one number per run)."""
        return tuple(AXES) if self.per_axis else ()

    @property
    def shown_unit(self) -> str:
        """The unit as a person reads it ('mg/°C'; a flag: '1 = yes')."""
        return FLAG_UNIT_WORDS if self.kind == "flag" else readable_unit(self.unit)

    def measured(self, value: object, axis: str | None = None, sigma: object = None,
                 source: str | None = None) -> Measurement:
        """This measurement's value on one run (a value or sigma that is no finite number: None)."""
        return Measurement(self.name, as_float(value), self.unit, axis, as_float(sigma),
                           self.source if source is None else source)

    def read(self, record: Mapping[str, object], axis: str | None = None) -> Measurement:
        """The value (key `name`) and its 1-sigma (key `sigma_key`) of a result's record."""
        return self.measured(record.get(self.name), axis, record.get(self.sigma_key) if self.sigma_key else None)


_DECLARED: dict[str, MeasurementDef] = {}


def declare(d: MeasurementDef) -> MeasurementDef:
    """Add a measurement. A name already declared differently is refused; declaring the same one
    again changes nothing."""
    other = _DECLARED.get(d.name)
    if other is not None and other != d:
        raise ValueError(f"measurement {d.name!r} is already declared differently: {other}")
    _DECLARED[d.name] = d
    return d


def undeclare(name: str) -> None:
    """Remove a measurement (a test's own); an unknown name is no error."""
    _DECLARED.pop(name, None)


@contextmanager
def declared_for_now(d: MeasurementDef) -> Iterator[MeasurementDef]:
    """`d` declared inside the block only (a test's measurement)."""
    new = d.name not in _DECLARED
    declare(d)
    try:
        yield d
    finally:
        if new:
            undeclare(d.name)


def declared() -> tuple[MeasurementDef, ...]:
    """Every declared measurement, in declaration order."""
    return tuple(_DECLARED.values())


def declaration(name: str) -> MeasurementDef | None:
    """The declaration of `name`; None for a name nobody declared (a site's own limit)."""
    return _DECLARED.get(name)


def is_per_axis(name: str) -> bool:
    d = _DECLARED.get(name)
    return d is not None and d.per_axis


def is_flag(name: str) -> bool:
    d = _DECLARED.get(name)
    return d is not None and d.kind == "flag"


def required_by(requirer: Requirer) -> tuple[MeasurementDef, ...]:
    """What `requirer` (a profile's analysis, or its program and verify) requires, in declaration order."""
    return tuple(d for d in _DECLARED.values() if requirer in d.required_by)


def in_section(section: Section) -> tuple[MeasurementDef, ...]:
    return tuple(d for d in _DECLARED.values() if section and d.section == section)


# ---- the station's measurements (docs/verdicts.md "Limits as data") ---------------------------------
_TD_SIGMA = ("the offline fit's own budget (station/science/offline_fit.py): each orientation's slope through block "
             "means with fit scatter, the part's bias wander, the temperature quantiser and MEMS lag, through eqs. 8/9")
_E_SIGMA = ("station/science/residual.py: the curvature's sigma (weighted parabola on block means) and what the "
            "coefficient sigmas leave over the operating range at 1 g")

TDB = declare(MeasurementDef(
    "tdb_mg_per_c", "mg/C", "TDB", "TDB", True, "signed", _TD_SIGMA, "offline",
    section="axes", sigma_key="tdb_sigma_mg_per_c", required_by=("thermal",), test_number=1000))
TDSF = declare(MeasurementDef(
    "tdsf_ppm_per_c", "ppm/C", "TDSF", "TDSF", True, "signed", _TD_SIGMA, "offline",
    section="axes", sigma_key="tdsf_sigma_ppm_per_c", required_by=("thermal",), test_number=1010))
FIT_AGREEMENT_TDB = declare(MeasurementDef(
    "fit_agreement_tdb_mg_per_c", "mg/C", "streaming vs offline TDB", "streaming vs offline TDB", True, "size",
    "", "streaming vs offline", test_number=1020))
FIT_AGREEMENT_TDSF = declare(MeasurementDef(
    "fit_agreement_tdsf_ppm_per_c", "ppm/C", "streaming vs offline TDSF", "streaming vs offline TDSF", True, "size",
    "", "streaming vs offline", test_number=1030))
DRIFT_ERROR_FS = declare(MeasurementDef(
    "drift_error_fs_pct", "%FS", "drift E_FS", "drift error E_FS", True, "size", _E_SIGMA + ", in %FS (eq. 12)",
    "eqs. 10-12", section="residual", sigma_key="drift_error_fs_sigma_pct", required_by=("thermal",),
    test_number=1040))
DRIFT_ERROR = declare(MeasurementDef(
    "drift_error_mg", "mg", "drift E", "drift error", True, "size", _E_SIGMA, "eq. 10",
    section="residual", sigma_key="drift_error_sigma_mg", test_number=1050))
BOW = declare(MeasurementDef(
    "bow_mg", "mg", "curvature bow", "curvature (bow)", True, "size",
    "sigma_c2 R^2/8 of the weighted parabola on block means (station/science/residual.py)", "curvature",
    section="residual", sigma_key="bow_sigma_mg", required_by=("thermal",), test_number=1060))
RAMP_RESIDUAL = declare(MeasurementDef(
    "ramp_residual_rms_mg", "mg", "ramp residual", "ramp residual RMS", True, "size", "", "own ramp",
    section="residual", test_number=1070))
NOISE = declare(MeasurementDef(
    "noise_ug_per_sqrt_hz", "ug/sqrt(Hz)", "noise", "noise density", True, "size", "", "stable samples",
    analysis="any", section="residual", test_number=1080))
SFEM_BIAS = declare(MeasurementDef(
    "sfem_bias_mg", "mg", "bias", "SFEM bias", True, "signed",
    "the SFEM fit's bias_sigma of the judged step (station/science/sfem_model.py), in mg", "sfem step",
    analysis="sfem", required_by=("sfem",), test_number=2000))
SFEM_SCALE_ERROR = declare(MeasurementDef(
    "sfem_scale_error_pct", "%", "scale error", "SFEM scale error", True, "size",
    "the SFEM fit's scale_sigma of the judged step, in %", "sfem step", analysis="sfem", required_by=("sfem",),
    test_number=2010))
SFEM_HELDOUT_RMSE = declare(MeasurementDef(
    "sfem_heldout_rmse_mg", "mg", "SFEM held-out RMSE", "SFEM held-out |a| - 1 g RMSE", False, "size", "",
    "sfem step", analysis="sfem", test_number=2020))
SFEM_RESIDUAL_RATIO = declare(MeasurementDef(
    "sfem_residual_ratio", "x noise", "SFEM residual / noise", "SFEM residual / noise", False, "ratio", "",
    "sfem step", analysis="sfem", test_number=2030))
LOST_SAMPLES = declare(MeasurementDef(
    "lost_samples_pct", "%", "lost samples", "lost samples", False, "size", "", "link", analysis="any",
    required_by=("thermal", "sfem"), test_number=3010))
LINK_ERRORS = declare(MeasurementDef(
    "link_errors", "frames", "link errors", "link errors", False, "count", "", "link", analysis="any",
    test_number=3000))
PROGRAM_CRC_MATCH = declare(MeasurementDef(
    "program_crc_match", "", "readback CRC equal to the written one", "readback CRC equal to written", False, "flag",
    "", "program", analysis="any", required_by=("program_verify", "sfem_program"), contract=(1.0, 1.0), test_number=4000))
COMPENSATION_ON = declare(MeasurementDef(
    "compensation_on", "", "on-board compensation on", "compensation on", False, "flag", "", "CALR after COMP 1",
    analysis="any", required_by=("program_verify", "sfem_program"), contract=(1.0, 1.0), test_number=4010))
VERIFIED_DRIFT_ERROR_FS = declare(MeasurementDef(
    "verified_drift_error_fs_pct", "%FS", "verified drift E_FS", "verified drift error E_FS", True, "size",
    "station/science/verify.py: spread of E under the (b1, b2) covariance (block scatter and the part's bias wander), "
    "fixed-seed Monte Carlo", "program-and-verify", analysis="any", required_by=("program_verify",), test_number=4020))
VERIFY_FAILED_AXES = declare(MeasurementDef(
    "verify_failed_axes", "axes", "axes failing the verification", "axes failing verification", False, "count", "",
    "program-and-verify", analysis="any", required_by=("program_verify", "sfem_program"), contract=(None, 0.0), test_number=4030))

# Issue 42. SFEM program and verify: the board's compensated output against the station's model over the
# cool-down, per axis (station/daemon/sfem_program.py); figures beside the contract's verify_failed_axes
_SFEM_VERIFY_SIGMA = ("station/daemon/sfem_program.py: the station model's own prediction sigma (its coefficient sigmas "
                      "and polynomial misfit), the block means' noise, the part's bias wander and the board's 1 C "
                      "temperature steps")
SFEM_VERIFIED_RESIDUAL_RMS = declare(MeasurementDef(
    "sfem_verified_residual_rms_mg", "mg", "SFEM on the board: residual rms", "SFEM verified residual rms", True,
    "size", _SFEM_VERIFY_SIGMA, "program-and-verify", analysis="sfem"))
SFEM_VERIFIED_RESIDUAL_MAX = declare(MeasurementDef(
    "sfem_verified_residual_max_mg", "mg", "SFEM on the board: residual max", "SFEM verified residual max", True,
    "size", _SFEM_VERIFY_SIGMA, "program-and-verify", analysis="sfem"))


__all__ = ["Measurement", "MeasurementDef", "Kind", "KINDS", "declare", "undeclare", "declared_for_now", "declared",
           "declaration", "is_per_axis", "is_flag", "required_by", "in_section", "finite", "as_float", "readable_unit",
           "UNIT_WORDS", "FLAG_UNIT_WORDS", "TDB", "TDSF", "FIT_AGREEMENT_TDB", "FIT_AGREEMENT_TDSF", "DRIFT_ERROR_FS",
           "DRIFT_ERROR", "BOW", "RAMP_RESIDUAL", "NOISE", "SFEM_BIAS", "SFEM_SCALE_ERROR", "SFEM_HELDOUT_RMSE",
           "SFEM_RESIDUAL_RATIO", "LOST_SAMPLES", "LINK_ERRORS", "PROGRAM_CRC_MATCH", "COMPENSATION_ON",
           "VERIFIED_DRIFT_ERROR_FS", "VERIFY_FAILED_AXES", "SFEM_VERIFIED_RESIDUAL_RMS", "SFEM_VERIFIED_RESIDUAL_MAX"]
