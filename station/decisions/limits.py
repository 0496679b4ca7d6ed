"""Spec limits as data: per product, versioned, with marginal bands and grades (bins).

A product is what the line builds: a sensor type (matched on the board's identity `sensor`) and,
optionally, part numbers. Its limits set has a name and a version that are stored with every DUT
run, so a verdict can always be traced to the numbers it was judged against. A site overrides or
adds products under `[products.NAME]` in the station TOML; a site product with a built-in's name
replaces it (bump `version` when you change a number).

Measurement names (units in the names, per axis x/y/z unless said otherwise), see station/decisions/verdicts.py:
    tdb_mg_per_c, tdsf_ppm_per_c            thermal coefficients (offline fit, with 1-sigma)
    drift_error_fs_pct, drift_error_mg      residual drift after compensation over the operating
                                            range, eqs. 10-12, predicted from the fit (with 1-sigma)
    bow_mg                                  curvature the linear model cannot compensate (model failure)
    ramp_residual_rms_mg                    the DUT's own ramp data about the compensated model
    fit_agreement_tdb_mg_per_c, fit_agreement_tdsf_ppm_per_c   |streaming - offline|
    noise_ug_per_sqrt_hz                    noise density
    lost_samples_pct, link_errors           per DUT (no axis)
    sfem_bias_mg, sfem_scale_error_pct      SFEM (sensors2023) bias and |scale - 1|
    verified_drift_error_fs_pct             E of the compensated output measured by program-and-verify
    verify_failed_axes                      axes whose compensated output fails the verification rules
    program_crc_match, compensation_on      1/0: readback CRC equal to the written one; compensation on
                                            (fixed contract checks of a verified profile, station/decisions/verdicts.py)

Version 2 of the built-in sets (this change): grades are judged with the spec's systematic term and
a part meeting no grade is its own outcome (no_grade_tray), not the last grade.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

AxisName = Literal["x", "y", "z"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Limit(_Model):
    """One limit on one measurement: low and/or high, optional marginal band inside them.

    A value inside [low, high] but within `marginal` of either end is `marginal`; so is a value
    whose uncertainty interval (value +- guard_sigma * sigma) crosses a limit, on either side;
    outside (interval included) is `fail`. sigma = sqrt(sigma_measured^2 + u_sys^2). With
    `evidence_sigma` > 0 the limit is a model check (the curvature a linear model cannot
    compensate): a crossing interval is `marginal` only when |value| >= evidence_sigma * sigma.
    """

    measurement: str = Field(min_length=1, max_length=64)
    axes: list[AxisName] | None = Field(default=None, description="per-axis measurements: which axes (None = all)")
    low: float | None = None
    high: float | None = None
    marginal: float = Field(default=0.0, ge=0, description="band inside the limits that is marginal, same unit")
    u_sys: float = Field(default=0.0, ge=0, description="systematic standard uncertainty added in quadrature to "
                         "the measurement's own 1-sigma before the guard band (same unit)")
    unit: str = ""
    label: str = Field(default="", description="plain words for the operator, e.g. 'TDSF'")
    required: bool = Field(default=False, description="missing measurement -> verdict error")
    analysis: Literal["thermal", "sfem", "any"] = "thermal"
    evidence_sigma: float = Field(default=0.0, ge=0, description=(
        "a model check, not a spec value: an interval that crosses the limit holds the part only when "
        "the value is at least this many of its own sigmas from zero (the data reject the model); "
        "0 = a plain guard-banded limit"))

    @model_validator(mode="after")
    def _bounds(self) -> "Limit":
        if self.low is None and self.high is None:
            raise ValueError(f"limit on {self.measurement!r} needs low and/or high")
        if self.low is not None and self.high is not None and self.low > self.high:
            raise ValueError(f"limit on {self.measurement!r}: low {self.low:g} > high {self.high:g}")
        return self


class Grade(_Model):
    """A bin: a passing DUT whose every interval lies inside these (tighter) limits gets it.

    Grades are tried in order; the last grade usually has no extra limits (= the spec itself)."""

    name: str = Field(min_length=1, max_length=16)
    tray: str = Field(default="", max_length=32, description="where the operator puts it (default: 'grade <name>')")
    limits: list[Limit] = []


class ProductSpec(_Model):
    """Limits set of one product: name + version are stored with every run judged by it."""

    name: str = Field(default="", max_length=64, description="limits-set name (default: the product key)")
    version: str = Field(default="1", min_length=1, max_length=32)
    sensor: str = Field(min_length=1, max_length=32, description="identity sensor this product uses")
    part_numbers: list[str] = []
    operating_range_c: float = Field(default=70.0, gt=0, description="Full Range of eq. 10 (martinez2022: -10..60 C)")
    guard_sigma: float = Field(default=2.0, ge=0, description="guard band: uncertainty interval = value +- k sigma")
    limits: list[Limit] = Field(min_length=1)
    grades: list[Grade] = [Grade(name="A")]
    reject_tray: str = "reject"
    marginal_tray: str = "hold (review / retest)"
    error_tray: str = "retest"
    no_grade_tray: str = Field(default="reject (no grade)", max_length=64,
                               description="a part inside the limits that meets no grade (verdict fail, grade 'none')")


def _lim(measurement: str, unit: str, label: str, low=None, high=None, marginal=0.0, required=False,
         analysis="thermal", axes=None, u_sys=0.0, evidence_sigma=0.0) -> Limit:
    return Limit(measurement=measurement, unit=unit, label=label, low=low, high=high, marginal=marginal,
                 required=required, analysis=analysis, axes=axes, u_sys=u_sys, evidence_sigma=evidence_sigma)


# The curvature hold needs the data to reject the linear model: |bow| >= 4 of its sigmas (the
# verification's own curvature rule, VerifyCriteria.curvature_sigma). Chosen against truth on
# simulated parts (benchmarks/curvature_holds.py): the bow sigma under-covers the simulator's
# errors by up to 1.6x (docs/verdicts.md "Curvature"), so the nominal 1 % point (z 3.1 over three
# axes) would hold 5-8 % of linear parts; at 4 sigma the hold rate of linear parts is the figure
# that benchmark prints, and parts bowing twice the limit are still held.
CURVATURE_EVIDENCE_SIGMA = 4.0


# Systematic uncertainty of the fast-thermal coefficients, i.e. only what no DUT's own sigma can
# hold (docs/verdicts.md "Uncertainty budget"). The DUT's sigma now carries bias wander, the 1 C
# quantiser, MEMS lag and the fit (benchmarks/coverage.py: 2u covers 94-98 % of simulated errors,
# RMS(error/u) 0.86-0.95, without u_sys). What is left is common to every DUT of a sensor lot and
# invisible in any one record: the scale of the on-die temperature reading against true C (TD is
# per reading-degree; compensation on the board uses the same reading, so it is harmless there,
# but the coefficient judged against a datasheet limit in mg per true C carries it). Taken as
# 0.1 % of the largest coefficient the limits allow (1.5 mg/C, 500 ppm/C): an assumption until a
# reference-chamber run of one lot measures it; the simulator has no such error, so coverage
# benchmarks report with and without it.
U_SYS_TDB_MG_PER_C = 1.5e-3
U_SYS_TDSF_PPM_PER_C = 0.5


def _common(noise_high: float, lost_pct: float = 1.0, link_errors: float = 50) -> list[Limit]:
    return [
        _lim("fit_agreement_tdb_mg_per_c", "mg/C", "streaming vs offline TDB", high=0.15),
        _lim("fit_agreement_tdsf_ppm_per_c", "ppm/C", "streaming vs offline TDSF", high=150.0),
        _lim("noise_ug_per_sqrt_hz", "ug/sqrt(Hz)", "noise", high=noise_high, analysis="any"),
        _lim("lost_samples_pct", "%", "lost samples", high=lost_pct, analysis="any"),
        _lim("link_errors", "frames", "link errors", high=link_errors, analysis="any"),
        _lim("verified_drift_error_fs_pct", "%FS", "verified drift E_FS", high=1.0, analysis="any"),
        # program and verify: axes whose compensated output still drifts (ratio or curvature rule)
        _lim("verify_failed_axes", "axes", "axes failing the verification", high=0.0, analysis="any"),
    ]


def default_products() -> dict[str, ProductSpec]:
    """Built-in limits (sources in the comments); a site replaces them in its config."""
    lis3dsh = ProductSpec(
        name="LIS3DSH-default", version="2", sensor="LIS3DSH",
        limits=[
            # martinez2022 Table 6 (LIS3DSH population): TDB -1.2..1.4 mg/C -> +-1.5 mg/C
            _lim("tdb_mg_per_c", "mg/C", "TDB", low=-1.5, high=1.5, marginal=0.05, required=True,
                 u_sys=U_SYS_TDB_MG_PER_C),
            # Table 6: TDSF 0..-500 ppm/C (positive values are clamped to 0 by the method)
            _lim("tdsf_ppm_per_c", "ppm/C", "TDSF", low=-500.0, marginal=10.0, required=True,
                 u_sys=U_SYS_TDSF_PPM_PER_C),
            # Table 7: after the fast compensation every axis but one is under 1 % FS (eq. 12)
            _lim("drift_error_fs_pct", "%FS", "drift E_FS", high=1.0, marginal=0.05, required=True),
            # a bow over 3 mg over 70 C is a model the data reject (linear parts here bow < ~1 mg);
            # held only on evidence of curvature (docs/verdicts.md "Curvature")
            _lim("bow_mg", "mg", "curvature bow", high=3.0, required=True, evidence_sigma=CURVATURE_EVIDENCE_SIGMA),
            _lim("ramp_residual_rms_mg", "mg", "ramp residual", high=1.5),
            # LIS3DSH datasheet zero-g offset +-60 mg typ. (sensors2023 Table 6 spreads to ~80 mg)
            _lim("sfem_bias_mg", "mg", "bias", low=-100.0, high=100.0, analysis="sfem"),
            _lim("sfem_scale_error_pct", "%", "scale error", high=5.0, analysis="sfem"),
            # datasheet 150 ug/sqrt(Hz) typ.; the station's estimate at 3.125 Hz ODR includes the
            # 60 ug quantization (~400 on the simulated boards): 600 catches a noisy part
            *_common(noise_high=600.0),
        ],
        grades=[
            Grade(name="A", limits=[
                _lim("drift_error_fs_pct", "%FS", "drift E_FS", high=0.5),  # Table 7 mean 0.61 %
                _lim("tdb_mg_per_c", "mg/C", "TDB", low=-1.0, high=1.0),
            ]),
            Grade(name="B"),
        ],
    )
    adxl355 = ProductSpec(
        name="ADXL355-default", version="2", sensor="ADXL355",
        limits=[
            # ADXL355 datasheet: offset vs temperature +-0.15 mg/C max
            _lim("tdb_mg_per_c", "mg/C", "TDB", low=-0.15, high=0.15, marginal=0.01, required=True,
                 u_sys=U_SYS_TDB_MG_PER_C),
            # datasheet: sensitivity change +-0.01 %/C = +-100 ppm/C
            _lim("tdsf_ppm_per_c", "ppm/C", "TDSF", low=-100.0, high=100.0, marginal=5.0, required=True,
                 u_sys=U_SYS_TDSF_PPM_PER_C),
            _lim("drift_error_fs_pct", "%FS", "drift E_FS", high=0.25, marginal=0.02, required=True),
            _lim("bow_mg", "mg", "curvature bow", high=1.0, required=True, evidence_sigma=CURVATURE_EVIDENCE_SIGMA),
            _lim("ramp_residual_rms_mg", "mg", "ramp residual", high=0.5),
            _lim("sfem_bias_mg", "mg", "bias", low=-75.0, high=75.0, analysis="sfem"),  # datasheet +-75 mg
            _lim("sfem_scale_error_pct", "%", "scale error", high=2.0, analysis="sfem"),
            # datasheet 25 ug/sqrt(Hz)
            *_common(noise_high=40.0),
        ],
        grades=[
            Grade(name="A", limits=[_lim("drift_error_fs_pct", "%FS", "drift E_FS", high=0.1)]),
            Grade(name="B"),
        ],
    )
    return {"LIS3DSH": lis3dsh, "ADXL355": adxl355}


def resolve_products(site: dict[str, ProductSpec]) -> dict[str, ProductSpec]:
    """The site's products first (a sensor match finds them before a built-in), then the built-ins
    the site did not replace (same key); every spec gets its name (default: its key)."""
    out = dict(site)
    for key, spec in default_products().items():
        out.setdefault(key, spec)
    for key, spec in out.items():
        if not spec.name:
            spec.name = key
    return out


def product_for(products: dict[str, ProductSpec], sensor: str | None, part_number: str | None = None) -> ProductSpec | None:
    """The product of a DUT: a part-number match first, else the first product of its sensor (site
    products come before the built-ins)."""
    if part_number:
        for spec in products.values():
            if part_number in spec.part_numbers:
                return spec
    for spec in products.values():
        if sensor and spec.sensor.lower() == sensor.lower():
            return spec
    return None


__all__ = ["Limit", "Grade", "ProductSpec", "default_products", "resolve_products", "product_for"]
