"""Response models of a DUT's calibration result as the daemon computes it (the live batch status
`slots[].result`): thermal (station/daemon/results.py thermal_result = `station calibrate --json`,
station/science/thermal_calibration.py calibrate) or SFEM (station/daemon/results.py sfem_result).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from web.schemas_common import PerAxis, ThermalAxes, _Out, free_form, passed_through


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


class SfemCalibration(_Out):
    """SFEM result of one DUT: the record contracts/sfem_result.py SfemResult (the same JSON as
    `station sfem --json`): the reference step's fit at the top level (A, b, scale, bias,
    misalignment, nonorthogonality, rmse_*_mg, goodness_of_fit, ...) plus the record's keys."""

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


CalibrationResult = ThermalCalibration | SfemCalibration
CalibrationResultJson = passed_through(ThermalCalibration, SfemCalibration)  # documented, not validated at runtime
