"""Response models of a DUT's calibration result as the daemon computes it (the live batch status
`slots[].result`): thermal (station/daemon/results.py thermal_result = `station calibrate --json`,
station/science/thermal_calibration.py calibrate) or SFEM (station/daemon/results.py sfem_result).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from contracts.selfcal_opinion import SELFCAL_OPINION_SHAPE
from web.schemas_common import PerAxis, ThermalAxes, _Out, free_form, one_of, passed_through


class OrientationDrift(_Out):
    """The total drift seen in one orientation of one axis (contracts/types.py OrientationDrift)."""

    orientation: int = Field(description="orientation index (0, 1, ...)")
    td_mg_per_c: float | None = Field(default=None, description="total drift TDB + TDSF * acc0, mg/C")
    acc0_g: float | None = Field(default=None, description="the axis's reading at the reference temperature, g")


class ThermalMethodResult(_Out):
    """One method's result (contracts/types.py ThermalResult.to_json); {"error": ...} alone when the
    live calibrator had none."""

    method: str | None = Field(default=None, description="streaming or offline")
    n_segments: int | None = Field(default=None, description="segments the result is computed from")
    axes: ThermalAxes | None = Field(default=None, description="TDB/TDSF per axis")
    orientations: dict[str, list[OrientationDrift]] | None = Field(
        default=None, description="per axis (x, y, z): the drift seen in each orientation")
    error: str | None = Field(default=None, description="why there is no result (streaming_live only)")


class SegmentRecord(_Out):
    """One averaged stable segment (contracts/types.py Segment)."""

    index: int = Field(description="segment index in the run")
    orientation: int | None = Field(default=None, description="orientation index")
    n_samples: int | None = Field(default=None, description="samples averaged")
    t_start_s: float | None = Field(default=None, description="board time of its first sample, s")
    t_end_s: float | None = Field(default=None, description="board time of its last sample, s")
    acc_mean_g: list[float | None] | None = Field(default=None, description="mean acceleration x, y, z, g")
    acc_std_g: list[float | None] | None = Field(default=None, description="standard deviation x, y, z, g")
    temp_mean_c: float | None = Field(default=None, description="mean temperature, C")
    temp_std_c: float | None = Field(default=None, description="temperature standard deviation, C")
    position: int | None = Field(default=None, description="plate position index, when known")


class CalibratorConfig(_Out):
    """The streaming calibrator's configuration (station/science/streaming_config.py StreamingConfig)."""

    alpha_acc: float | None = Field(default=None, description="acceleration low-pass coefficient (0..1)")
    alpha_gradient: float | None = Field(default=None, description="temperature-gradient low-pass coefficient")
    gradient_limit_c_per_min: float | None = Field(default=None, description="stable below this gradient, C/min")
    discard_samples: int | None = Field(default=None, description="samples discarded once stable")
    average_samples: int | None = Field(default=None, description="samples averaged into a segment")
    segment_delta_c: float | None = Field(default=None, description="temperature step between segments, C")
    orientation_delta_g: float | None = Field(default=None, description="change that marks a new orientation, g")
    gradient_reset_c_per_min: float | None = Field(default=None, description="gradient that restarts a segment, C/min")
    gradient_reset_signed: bool | None = Field(default=None, description="the reset gradient is signed")
    t_ref_c: float | None = Field(default=None, description="reference temperature, C")
    clamp_positive_tdsf: bool | None = Field(default=None, description="a positive TDSF is clamped to 0")
    detect_orientation_while_logging: bool | None = Field(default=None, description="orientation changes are "
                                                          "detected while a segment is logged")
    min_pair_delta_c: float | None = Field(default=None, description="least temperature span of a segment pair, C")


class ResidualAxis(_Out):
    """Residual drift of one axis after compensation (station/science/residual.py); null where the
    data do not allow a value."""

    drift_error_mg: float | None = Field(default=None, description="residual drift error E over the range, mg")
    drift_error_sigma_mg: float | None = Field(default=None, description="its 1-sigma, mg")
    drift_error_fs_pct: float | None = Field(default=None, description="E in % of full scale")
    drift_error_fs_sigma_pct: float | None = Field(default=None, description="its 1-sigma, % of full scale")
    drift_error_curvature_sigma_mg: float | None = Field(default=None, description="the curvature's part of "
                                                         "drift_error_sigma_mg (1-sigma), mg")
    curvature_mg_per_c2: float | None = Field(default=None, description="residual curvature, mg/C^2")
    curvature_sigma_mg_per_c2: float | None = Field(default=None, description="its 1-sigma, mg/C^2")
    bow_mg: float | None = Field(default=None, description="residual bow over the range, mg")
    bow_sigma_mg: float | None = Field(default=None, description="its 1-sigma, mg")
    noise_ug_per_sqrt_hz: float | None = Field(default=None, description="noise density, ug/sqrt(Hz)")
    ramp_residual_rms_mg: float | None = Field(default=None, description="RMS of the compensated ramp residual, mg")


class ResidualAxes(_Out):
    x: ResidualAxis | None = Field(default=None, description="x axis")
    y: ResidualAxis | None = Field(default=None, description="y axis")
    z: ResidualAxis | None = Field(default=None, description="z axis")


class ResidualReport(_Out):
    """station/science/residual.py residual_report."""

    operating_range_c: float | None = Field(default=None, description="range the drift error is judged over, C")
    odr_hz: float | None = Field(default=None, description="sample rate, Hz")
    n_used: int | None = Field(default=None, description="samples used")
    axes: ResidualAxes | None = Field(default=None, description="per axis")


class UncertaintyTerms(_Out):
    """The TD_i sigma budget of one orientation, per term: x, y, z each, mg/C."""

    fit: list[float | None] | None = Field(default=None, description="fit (batch means) x, y, z, mg/C")
    wander: list[float | None] | None = Field(default=None, description="bias wander x, y, z, mg/C")
    quantiser: list[float | None] | None = Field(default=None, description="temperature quantiser x, y, z, mg/C")
    lag: list[float | None] | None = Field(default=None, description="sensor lag x, y, z, mg/C")


class PartNoiseOut(_Out):
    """The part's own noise level the budget used (station/science/part_noise.py)."""

    source: str | None = Field(default=None, description="measured (on this part), class (the class constant: too "
                               "little still data) or given (fixed by the caller)")
    class_: str | None = Field(default=None, alias="class", description="the sensor class whose wander shape is used")
    scale: float | None = Field(default=None, description="the part's white noise density / the class's: the "
                                "factor on the class's random walk and flicker")
    n_still_samples: int | None = Field(default=None, description="still samples it was measured on")
    white_ug_per_sqrt_hz: list[float | None] | None = Field(default=None, description="white noise density x, y, z, "
                                                            "ug/sqrt(Hz)")
    wander_rw_g_per_sqrt_s: float | None = Field(default=None, description="the part's bias random walk, g/sqrt(s)")
    wander_flicker_g: float | None = Field(default=None, description="the part's bias flicker floor, g")


class UncertaintyBudget(_Out):
    """The budget behind the offline sigmas (station/science/offline_fit.py _uncertainty_doc)."""

    temperature_quantum_c: float | None = Field(default=None, description="temperature sensor step, C")
    temperature_dither_c: float | None = Field(default=None, description="temperature dither, C")
    wander: str | None = Field(default=None, description="the bias-wander class used (by sensor)")
    wander_rw_g_per_sqrt_s: float | None = Field(default=None, description="bias random walk, g/sqrt(s)")
    wander_flicker_g: float | None = Field(default=None, description="bias flicker floor, g")
    wander_flicker_tau_s: list[float] | None = Field(default=None, description="flicker time constants, s")
    part_noise: PartNoiseOut | None = Field(default=None, description="the part's own noise level")
    chord_x_c: dict[str, float] | None = Field(default=None, description="per orientation: what TD_i makes of a "
                                               "bias curvature c2 (TD_i moves by c2 x this; C)")
    lag_sigma_s: float | None = Field(default=None, description="1-sigma of the sensor lag, s")
    orientations: dict[str, UncertaintyTerms] = Field(default_factory=dict, description="per orientation index")
    tdb_tdsf_corr: PerAxis | None = Field(default=None, description="correlation of TDB and TDSF errors per axis (-1..1)")


class SelfCalSigmaTerms(_Out):
    """The 1-sigma terms of one board figure (station/science/selfcal_compare.py estimator_sigmas), in
    the figure's unit (mg/C for TDB, ppm/C for TDSF); their root sum of squares is u_board."""

    white: float | None = Field(default=None, description="from the part's white noise over the segments' samples")
    wander: float | None = Field(default=None, description="from the part's bias wander over the segments' times")
    quantiser: float | None = Field(default=None, description="from the temperature reading's steps and dither")


class SelfCalTermsAxes(_Out):
    """One figure's sigma terms per axis."""

    x: SelfCalSigmaTerms | None = Field(default=None, description="x axis")
    y: SelfCalSigmaTerms | None = Field(default=None, description="y axis")
    z: SelfCalSigmaTerms | None = Field(default=None, description="z axis")


class SelfCalTerms(_Out):
    """The board figures' sigma terms: TDB in mg/C, TDSF in ppm/C."""

    tdb_mg_per_c: SelfCalTermsAxes | None = Field(default=None, description="TDB's terms per axis, mg/C")
    tdsf_ppm_per_c: SelfCalTermsAxes | None = Field(default=None, description="TDSF's terms per axis, ppm/C")


class SelfCalNoise(_Out):
    """The part's noise the board's uncertainty was told with (station/science/selfcal_compare.py
    PartNoiseModel.to_json, + where the board's estimate comes from and its terms); {} when the
    comparison stopped before the noise was known."""

    sample_sigma_mg: list[float | None] | None = Field(default=None, description="per-sample white noise x, y, z, mg")
    wander: str | None = Field(default=None, description="the bias-wander class whose shape is used")
    wander_rw_g_per_sqrt_s: float | None = Field(default=None, description="the bias random walk used, g/sqrt(s)")
    wander_flicker_g: float | None = Field(default=None, description="the bias flicker floor used, g")
    temperature_quantum_c: float | None = Field(default=None, description="temperature reading's step, C")
    temperature_dither_c: float | None = Field(default=None, description="temperature reading's dither, C")
    source: str | None = Field(default=None, description="where each figure comes from, in words")
    board_estimate_from: str | None = Field(default=None, description="the segments the board's uncertainty is "
                                            "computed over (its own G segments, or the station's standing in)")
    terms: SelfCalTerms | None = Field(default=None, description="u_board's terms per figure and axis")


class SelfCalRow(_Out):
    """One figure of one axis side by side (contracts/selfcal_opinion.py OpinionRow.to_json); every
    value in `unit`. The row agrees when |difference| <= k x u_combined."""

    axis: str = Field(description="x, y or z")
    figure: str = one_of(("tdb_mg_per_c", "tdsf_ppm_per_c"), "which figure: TDB (mg/C) or TDSF (ppm/C)",
                         nullable=False)
    unit: str = one_of(("mg/C", "ppm/C"), "the unit of board, station, difference and the u's", nullable=False)
    board: float = Field(description="the board's own calibrator's figure, in `unit`")
    station: float = Field(description="the station's figure (its offline fit), in `unit`")
    difference: float = Field(description="board - station, in `unit`")
    u_board: float = Field(description="1-sigma of the board's figure under this part's noise, in `unit`")
    u_station: float | None = Field(default=None, description="1-sigma of the station's figure, in `unit` (null: "
                                    "its result carries none; then u_combined = u_board)")
    u_combined: float = Field(description="sqrt(u_board^2 + u_station^2), in `unit`")
    k: float = Field(description="the agreement limit in combined sigmas (|difference| <= k x u_combined)")
    agrees: bool = Field(description="|difference| <= k x u_combined")
    board_from_segments: float | None = Field(default=None, description="the same figure recomputed by the station "
                                              "from the board's own G segments, in `unit` (null: no G frames): "
                                              "tells a result that is off from data that are")
    clamped_board: bool = Field(default=False, description="the board clamped this positive TDSF to 0")
    clamped_station: bool = Field(default=False, description="the station clamped this positive TDSF to 0")


class BoardSelfCalOpinion(_Out):
    """The board's own calibrator against the station's result (issue 42, the profile option
    `board_selfcal`; contracts/selfcal_opinion.py SelfCalOpinion.to_json): what the verdict's check
    `board_selfcal_agrees` judges. Present on a slot's result once compared, for a board with a
    calibrator (caps `scal`)."""

    shape: str = one_of((SELFCAL_OPINION_SHAPE,), "the record's shape", nullable=False)
    applicable: bool = Field(description="the board has a calibrator (false: the check is not applicable, "
                             "never a fail; `note` says why)")
    error: str | None = Field(default=None, description="a capable board whose result could not be read or "
                              "compared: why (the check is then an error, never a pass); null otherwise")
    note: str = Field(default="", description="why the comparison does not apply ('' when it does)")
    agrees: bool = Field(description="applicable, no error, and every row agrees")
    rows: list[SelfCalRow] = Field(default_factory=list, description="TDB and TDSF of each axis side by side "
                                   "(empty when not applicable or on an error)")
    n_segments_board: int = Field(default=0, description="segments the board's calibrator used (its `R` reply)")
    n_segments_station: int = Field(default=0, description="segments the station's streaming calibrator logged")
    noise: SelfCalNoise = Field(default_factory=SelfCalNoise, description="the part's noise the board's "
                                "uncertainty was told with")
    assumptions: str = Field(default="", description="what the comparison assumes, in words")


class ThermalCalibration(_Out):
    """Thermal result of one DUT (`station calibrate --json`)."""

    serial: str | None = Field(default=None, description="the board's serial")
    sensor: str | None = Field(default=None, description="sensor type ('' when not known)")
    axes_method: str | None = Field(default=None, description="which method `axes` comes from (offline)")
    axes: ThermalAxes | None = Field(default=None, description="the result: TDB/TDSF per axis")
    streaming: ThermalMethodResult | None = Field(default=None, description="the streaming algorithm re-run on the samples")
    streaming_live: ThermalMethodResult | None = Field(default=None, description="the live calibrator's own result")
    offline: ThermalMethodResult | None = Field(default=None, description="the offline fit")
    segments: list[SegmentRecord] = Field(default_factory=list, description="the segments used")
    n_samples: int | None = Field(default=None, description="samples analysed")
    temperature_swing_c: float | None = Field(default=None, description="temperature span of the data, C")
    config: CalibratorConfig | None = Field(default=None, description="the calibrator configuration used")
    residual: ResidualReport | None = Field(default=None, description="residual drift after compensation")
    uncertainty: UncertaintyBudget | None = Field(default=None, description="the sigma budget")
    board_selfcal: BoardSelfCalOpinion | None = Field(default=None, description="the board's own calibrator "
                                                      "against this result (profile option board_selfcal, a board "
                                                      "with caps `scal`); absent otherwise")


class SfemMisalignment(_Out):
    """The reference step's misalignment (station/science/sfem_model.py SfemFit.to_json)."""

    determined: bool | None = Field(default=None, description="the positions determine it (else zero, `note` why)")
    rotvec_deg: list[float | None] | None = Field(default=None, description="rotation vector x, y, z, degrees")
    matrix: list[list[float | None]] | None = Field(default=None, description="the rotation matrix M (3x3)")
    rotvec_sigma_deg: list[float | None] | None = Field(default=None, description="1-sigma of rotvec_deg, degrees "
                                                        "(only when determined)")
    note: str | None = Field(default=None, description="why it is not determined, in words")


class SfemNonorthogonality(_Out):
    """The reference step's non-orthogonality angles (small-angle, rad)."""

    alpha_yx_rad: float | None = Field(default=None, description="y axis towards x, rad")
    alpha_zx_rad: float | None = Field(default=None, description="z axis towards x, rad")
    alpha_zy_rad: float | None = Field(default=None, description="z axis towards y, rad")
    sigma_rad: list[float | None] | None = Field(default=None, description="1-sigma of the three angles, rad")


class SfemGoodnessOut(_Out):
    """The reference step's residual against the part's noise (station/science/sfem_goodness.py)."""

    residual_ratio: float | None = Field(default=None, description="residual / what the noise predicts (null: not "
                                         "testable)")
    dof: int | None = Field(default=None, description="degrees of freedom left to test the model with")
    mark_ratio: float | None = Field(default=None, description="a ratio above this marks the fit")
    misses_effect: bool | None = Field(default=None, description="the model misses an effect the data show")
    words: str | None = Field(default=None, description="the finding in words")
    effect: str | None = Field(default=None, description="the named effect that explains the residual, if one does")
    effect_mg: list[float | None] | None = Field(default=None, description="that effect's size x, y, z, mg")
    ratio_with_effect: float | None = Field(default=None, description="the residual ratio once the effect is allowed "
                                            "for")


class SfemResidualRow(_Out):
    """One static position's residual after the fit."""

    norm_err_mg: float | None = Field(default=None, description="|A(u - b)| - 1 g, mg")
    direction_err_deg: float | None = Field(default=None, description="angle between A(u - b) and the position's "
                                            "reference direction, degrees")
    position: int | None = Field(default=None, description="plate position index (contracts/positions.py)")
    n_samples: int | None = Field(default=None, description="samples averaged at the position")


class SfemSkippedStep(_Out):
    """A temperature step left out of the SFEM (station/science/sfem_record.py)."""

    temp_c: float | None = Field(default=None, description="the step's temperature, C")
    n_positions: int | None = Field(default=None, description="static positions it had")
    reason: str | None = Field(default=None, description="why it was left out")


class SfemCalibration(_Out):
    """SFEM result of one DUT: the record contracts/sfem_result.py SfemResult (the same JSON as
    `station sfem --json`): the reference step's fit at the top level (A, b, scale, bias,
    misalignment, nonorthogonality, rmse_*_mg, goodness_of_fit, ...) plus the record's keys.
    Units are in the names; A dimensionless (raw -> g), b and bias in g, scale in g per raw unit."""

    # the reference step's fit (station/science/sfem_model.py SfemFit.to_json)
    method: str | None = Field(default=None, description="reference (positions with known directions) or norm-only")
    A: list[list[float | None]] | None = Field(default=None, description="A = M C S (3x3): raw -> g after b")
    A_sigma: list[list[float | None]] | None = Field(default=None, description="1-sigma of each element of A")
    b: list[float | None] | None = Field(default=None, description="bias x, y, z, in the readings' raw units (g "
                                         "for the station's logs)")
    misalignment: SfemMisalignment | None = Field(default=None, description="the misalignment M")
    nonorthogonality: SfemNonorthogonality | None = Field(default=None, description="the non-orthogonality C")
    scale: list[float | None] | None = Field(default=None, description="scale x, y, z, g per raw unit")
    scale_sigma: list[float | None] | None = Field(default=None, description="1-sigma of scale")
    bias: list[float | None] | None = Field(default=None, description="the same as b, g")
    bias_sigma: list[float | None] | None = Field(default=None, description="1-sigma of bias, g")
    rmse_before_mg: float | None = Field(default=None, description="RMS of |u| - 1 g before the fit, mg")
    rmse_after_mg: float | None = Field(default=None, description="RMS of |A(u - b)| - 1 g after the fit, mg")
    rmse_direction_mg: float | None = Field(default=None, description="RMS of |A(u - b) - r| over positions, mg "
                                            "(reference fits)")
    rmse_heldout_mg: float | None = Field(default=None, description="|a| - 1 g RMSE on what the fit never saw, mg")
    heldout_method: str | None = Field(default=None, description="how rmse_heldout_mg was held out, in words")
    n_positions: int | None = Field(default=None, description="static positions fitted")
    ref_sigma_deg: float | None = Field(default=None, description="1-sigma of a position's reference direction, deg")
    ref_sigma_source: str | None = Field(default=None, description="where ref_sigma_deg comes from, in words")
    goodness_of_fit: SfemGoodnessOut | None = Field(default=None, description="the residual against the noise")
    uncertainty_scaled: bool | None = Field(default=None, description="the covariance was rescaled by the reduced "
                                            "chi-square")
    success: bool | None = Field(default=None, description="the optimiser converged")
    residuals: list[SfemResidualRow] = Field(default_factory=list, description="per position")
    notes: list[str] = Field(default_factory=list, description="the fit's and the record's notes, in words")
    temperature_step: int | None = Field(default=None, description="index of this fit's step in steps")
    # the record's own keys

    shape: str = Field(description="the record's shape: sfem-record/1")
    t_ref_c: float = Field(description="the headline and the verdict use the step nearest this temperature, C")
    reference_step: int = Field(description="index in steps of the step nearest t_ref_c")
    temp_c: float | None = Field(default=None, description="mean temperature of the reference step, C")
    steps: list[dict[str, Any]] = free_form("one fit per temperature step, coldest first "
                                            "(station/science/sfem_model.py SfemFit.to_json + temperature_step)")
    thermal: dict[str, Any] | None = free_form("the polynomial thermal model (sensors2023 eq. 8, "
                                               "station/science/sfem_thermal.py), with drift_at_t_ref in the "
                                               "TDSF/TDB convention of martinez2022; null with one step", default=None)
    model_check: dict[str, Any] | None = free_form("the worst step's residual against the noise, in words "
                                                   "(station/science/sfem_goodness.py)", default=None)
    temperature_steps_c: list[float | None] = Field(default_factory=list, description="each step's mean temperature, "
                                                    "C, coldest first")
    n_static_intervals: int | None = Field(default=None, description="static intervals found in the run's samples")
    skipped_steps: list[SfemSkippedStep] = Field(default_factory=list, description="temperature steps left out")
    record_notes: list[str] = Field(default_factory=list, description="the record's own notes (also in notes)")


CalibrationResult = ThermalCalibration | SfemCalibration
CalibrationResultJson = passed_through(ThermalCalibration, SfemCalibration)  # documented, not validated at runtime
