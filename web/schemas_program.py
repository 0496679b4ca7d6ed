"""Response models of a DUT's program and verify, live and stored: the program record (thermal
coefficients, or the cubic SFEM of a version-2 record with its approximation error) and the
verification (eq. 13 over a heat rise, or the cubic SFEM against the station's prediction).

Kept apart from web/schemas_live.py (the batch's live status, which embeds these per slot) so each
module stays one subject. Producers: station/daemon/program_verify.py, station/daemon/sfem_program.py.
"""

from __future__ import annotations

from pydantic import Field

from station.decisions.board_checks import SFEM_CUBIC_KIND
from web.schemas_common import PerAxis, _Out, one_of, passed_through


class SfemCubicOut(_Out):
    """The cubic SFEM written into a board as its version-2 record (station/daemon/sfem_program.py
    record_json; docs/design.md 3.1): u_cal = A(T) (u - b(T)), each of A's 9 elements and
    b's 3 a cubic in (T - t_ref_c)."""

    t_ref_c: float = Field(description="the polynomials' reference temperature, C")
    t_lo_c: float = Field(description="lowest temperature the record holds for, C (the board clamps below)")
    t_hi_c: float = Field(description="highest temperature the record holds for, C (the board clamps above)")
    coef: list[list[float]] = Field(description="4 rows (power 0..3 of T - t_ref_c, per C^k) of 12 values: a11 a12 "
                                    "a13 a21 a22 a23 a31 a32 a33 (dimensionless), then b_x b_y b_z (g)")
    crc: str = Field(description="CRC-32 of the record as float32, as the station computed it (8 hex digits)")
    layout: str = Field(description="the layout of coef, in words")


class CubicApproximationOut(_Out):
    """How far the record as stored (float32 cubics) is from the station's SFEM model over its range
    (station/science/sfem_board_record.py CubicApproximation.to_json)."""

    t_lo_c: float | None = Field(default=None, description="range checked from, C")
    t_hi_c: float | None = Field(default=None, description="range checked to, C")
    max_a_error: float | None = Field(default=None, description="largest |A_record - A_model| of any element "
                                      "(dimensionless)")
    max_b_error_mg: float | None = Field(default=None, description="largest |b_record - b_model| of any axis, mg")
    max_output_error_mg: float | None = Field(default=None, description="largest error of the compensated output "
                                              "for a 1 g input, mg (the verification's limits include it)")
    worst_temp_c: float | None = Field(default=None, description="where max_output_error_mg is reached, C")
    check_points: int | None = Field(default=None, description="temperatures the error was checked at")
    what: str | None = Field(default=None, description="what the figures measure, in words")


class LiveProgram(_Out):
    """What the program step did to one board (station/daemon/program_verify.py, drivers/base.py
    ProgramReport.to_json); on a failure only programmed=false, error_kind, error (and what was tried)."""

    programmed: bool | None = Field(default=None, description="written, read back identical, compensation on")
    tdb_mg_per_c: list[float] | None = Field(default=None, description="TDB written x, y, z, mg/C")
    tdsf_ppm_per_c: list[float] | None = Field(default=None, description="TDSF written x, y, z, ppm/C")
    method: str | None = Field(default=None, description="which thermal result was written (offline, streaming)")
    crc: str | None = Field(default=None, description="CRC-32 of the written float32 values (8 hex digits)")
    readback_crc: str | None = Field(default=None, description="CRC-32 the board reports (8 hex digits)")
    readback_values: list[float] | None = Field(default=None, description="values read back (TDB x y z mg/C, TDSF "
                                                "x y z ppm/C, as float32)")
    readback_identical: bool | None = Field(default=None, description="crc == readback_crc")
    comp: bool | None = Field(default=None, description="the board's compensation is on")
    attempts: int | None = Field(default=None, description="write attempts used (1 = first try)")
    retries: list[str] | None = Field(default=None, description="why each failed attempt failed")
    comp_from_t: float | None = Field(default=None, description="board time, s, from which samples are compensated")
    error_kind: str | None = Field(default=None, description="why programming failed (refused, crc_mismatch, link, "
                                   "no_result, ...)")
    error: str | None = Field(default=None, description="the failure in words")
    # an SFEM profile's program step (issue 42, station/daemon/sfem_program.py)
    sfem_cubic: SfemCubicOut | str | None = Field(default=None, description="SFEM profiles: the cubic SFEM written "
                                                  "(or meant to be: on a failure, what was tried); a string on a "
                                                  "board without the version-2 record (caps `sfem3`): why it was "
                                                  "not programmed")
    approximation: CubicApproximationOut | None = Field(default=None, description="SFEM profiles: how far the record "
                                                        "is from the station's model over its range")
    not_applicable: bool | None = Field(default=None, description="SFEM profiles: true on a board that stores no "
                                        "version-2 record: not programmed, not verified, judged as an SFEM run "
                                        "without program and verify")


class AxisVerificationOut(_Out):
    """The verified drift of one axis (station/science/verify.py AxisVerification)."""

    axis: str = Field(description="x, y or z")
    e_before_mg: float | None = Field(default=None, description="drift error E before compensation, mg")
    e_after_mg: float | None = Field(default=None, description="drift error E with compensation, mg")
    ratio: float | None = Field(default=None, description="e_after / e_before")
    residual_range_mg: float | None = Field(default=None, description="max - min of the compensated section means, mg")
    curvature_mg_per_c2: float | None = Field(default=None, description="residual curvature, mg/C^2")
    curvature_sigma_mg_per_c2: float | None = Field(default=None, description="its 1-sigma, mg/C^2")
    curvature_bow_mg: float | None = Field(default=None, description="residual bow over the full range, mg")
    curved: bool | None = Field(default=None, description="the bow is over its limit and significant")
    passed: bool | None = Field(default=None, description="this axis passed")
    reason: str = Field(default="", description="why not, in words")
    e_after_sigma_mg: float | None = Field(default=None, description="1-sigma of e_after_mg, mg")


class VerifyCriteriaOut(_Out):
    """The pass rule of the verification (station/science/verify.py VerifyCriteria)."""

    e_ratio_max: float | None = Field(default=None, description="E after at most this fraction of E before ...")
    e_floor_mg: float | None = Field(default=None, description="... or at most this, mg")
    full_range_c: float | None = Field(default=None, description="temperature range E is scaled to, C")
    section_c: float | None = Field(default=None, description="width of a thermal section of the ramp, C")
    min_section_samples: int | None = Field(default=None, description="samples a section needs")
    curvature_limit_mg: float | None = Field(default=None, description="residual bow that flags a part, mg")
    curvature_sigma: float | None = Field(default=None, description="... when this many sigmas from zero")
    min_rise_c: float | None = Field(default=None, description="a verification heating less cannot judge, C")
    range_centre_c: float | None = Field(default=None, description="centre of the judged range, C")
    block_s: float | None = Field(default=None, description="batch-means block of the fit, s")
    e_sigma_k: float | None = Field(default=None, description="an axis fails when E - k sigma is over its limit")
    odr_hz: float | None = Field(default=None, description="sample rate assumed without sample times, Hz")


class LiveVerification(_Out):
    """The verification of one programmed board (station/science/verify.py VerificationResult.to_json
    + step_index, duration_s, before_source); when it cannot be computed: passed=false, flags, null E."""

    passed: bool = Field(description="the compensation works on this part")
    flags: list[str] = Field(default_factory=list, description="named problems, or why it was not verified")
    rise_c: float | None = Field(default=None, description="temperature rise of the verification heat, C")
    temp_from_c: float | None = Field(default=None, description="temperature at its start, C")
    temp_to_c: float | None = Field(default=None, description="temperature at its end, C")
    n_samples: int | None = Field(default=None, description="compensated samples judged")
    n_sections: int | None = Field(default=None, description="thermal sections of the ramp")
    e_before_mg: PerAxis | None = Field(default=None, description="E before compensation per axis, mg")
    e_after_mg: PerAxis | None = Field(default=None, description="E with compensation per axis, mg")
    e_after_sigma_mg: PerAxis | None = Field(default=None, description="1-sigma of E after per axis, mg")
    e_after_fs_pct: PerAxis | None = Field(default=None, description="E after per axis, % of full scale")
    e_after_fs_sigma_pct: PerAxis | None = Field(default=None, description="its 1-sigma, % of full scale")
    range_c: list[float] | None = Field(default=None, description="judged temperature range [low, high], C")
    axes: dict[str, AxisVerificationOut] = Field(default_factory=dict, description="per axis (x, y, z) detail; "
                                                 "empty when not computed")
    criteria: VerifyCriteriaOut | None = Field(default=None, description="the pass rule applied")
    step_index: int | None = Field(default=None, description="the heat step verified")
    duration_s: float | None = Field(default=None, description="sample seconds of that step")
    before_source: str | None = Field(default=None, description="where E before comes from, in words")


class SfemResidualTerms(_Out):
    """The 1-sigma terms of one axis's block residual, mg (station/daemon/sfem_program.py _sigma_terms);
    their root sum of squares is sigma_mg."""

    model: float | None = Field(default=None, description="the station model's own parameter sigmas through its "
                                "polynomial, mg")
    misfit: float | None = Field(default=None, description="the steps' scatter about each parameter's polynomial, mg")
    noise: float | None = Field(default=None, description="the block means' and the prediction's white noise, mg")
    wander: float | None = Field(default=None, description="the sensor class's bias wander over the run, mg")
    quantiser: float | None = Field(default=None, description="the board's stepped temperature reading, mg")


class SfemAxisVerification(_Out):
    """One axis of the cubic SFEM verified on the board: its compensated output's block means against
    the station's prediction, with the run's own limits (all mg)."""

    passed: bool | None = Field(default=None, description="rms and max within their limits")
    residual_rms_mg: float | None = Field(default=None, description="rms of the block residuals, mg")
    residual_max_mg: float | None = Field(default=None, description="largest |block residual|, mg")
    residual_mean_mg: float | None = Field(default=None, description="mean block residual, mg")
    limit_rms_mg: float | None = Field(default=None, description="k_rms x sigma + approximation + one count, mg")
    limit_max_mg: float | None = Field(default=None, description="k_max x sigma + approximation + one count, mg")
    sigma_mg: float | None = Field(default=None, description="1-sigma of a block residual, mg")
    terms_mg: SfemResidualTerms | None = Field(default=None, description="sigma_mg's terms, mg")


class SfemResidualBlocks(_Out):
    """The block residuals over temperature, one entry per block."""

    temp_c: list[float] = Field(default_factory=list, description="each block's mean temperature, C")
    x: list[float] = Field(default_factory=list, description="x residual per block, mg")
    y: list[float] = Field(default_factory=list, description="y residual per block, mg")
    z: list[float] = Field(default_factory=list, description="z residual per block, mg")


class SfemVerification(_Out):
    """The cubic SFEM verified on the board (issue 42, station/daemon/sfem_program.py verify_one): while
    the plate cools through the record's range, the board's compensated output against the station's
    prediction for the plate's position. When it cannot be judged: passed=false, flags say why, axes empty."""

    kind: str = one_of((SFEM_CUBIC_KIND,), "the verification's kind", nullable=False)
    passed: bool = Field(description="every axis within its limits")
    flags: list[str] = Field(default_factory=list, description="named problems (an axis over its limits, a plate "
                             "that hardly moved), or why it was not verified")
    axes: dict[str, SfemAxisVerification] = Field(default_factory=dict, description="per axis (x, y, z); empty when "
                                                  "not computed")
    prediction_g: list[float] | None = Field(default=None, description="the output predicted at the position, x y z, g")
    prediction_temp_c: float | None = Field(default=None, description="mean temperature of the samples the "
                                            "prediction comes from, C")
    prediction_from: str | None = Field(default=None, description="where the prediction comes from, in words")
    temp_range_c: list[float] | None = Field(default=None, description="temperatures the verified blocks span "
                                             "[low, high], C")
    record_range_c: list[float] | None = Field(default=None, description="the record's range [t_lo, t_hi], C")
    n_samples: int | None = Field(default=None, description="compensated samples within the record's range judged")
    n_outside_range: int | None = Field(default=None, description="compensated samples outside the record's range "
                                        "(the board clamps there): not judged")
    n_blocks: int | None = Field(default=None, description="block means judged")
    block_s: float | None = Field(default=None, description="length of a block, sample seconds")
    window_s: list[float] | None = Field(default=None, description="board time of the first and last judged "
                                         "sample [from, to], s")
    approx_error_mg: float | None = Field(default=None, description="the record's own approximation error, mg "
                                          "(in the limits)")
    k_rms: float | None = Field(default=None, description="the rms limit in sigmas")
    k_max: float | None = Field(default=None, description="the max limit in sigmas")
    residual_blocks: SfemResidualBlocks | None = Field(default=None, description="the block residuals over "
                                                       "temperature, mg")


# documented, not validated at runtime (passed_through): a thermal profile's verification or an SFEM one's
LiveVerificationJson = passed_through(LiveVerification, SfemVerification)
