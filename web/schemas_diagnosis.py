"""Response models of the model diagnostics of a stored run (GET /api/runs/{id}/diagnosis and its
model.json): design 5.2 JSON (station/diagnostics/ranking.py DiagnosisReport.to_json, with plots,
library and noise from web/diag_plots.py report_json), and the fitted model
(station/diagnostics/model.py DiagnosticModel.to_json).

Maps keyed by serial, parameter or effect name are typed maps; the Allan-deviation noise view per
DUT (station/diagnostics/noise_view.py, a plot's data) is a documented free-form object.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from web.schemas_common import PerAxisBool, _Out, free_form


class ModelFigures(_Out):
    """How well a model fits (station/diagnostics/ranking.py _eval_json): residual RMS in mg."""

    rms_mg: float | None = Field(default=None, description="in-sample RMS of the residual (rms_basis means), mg")
    heldout_rms_mg: float | None = Field(default=None, description="held-out RMS (whole thermal legs), mg")
    rms_per_sample_mg: float | None = Field(default=None, description="in-sample RMS per sample, mg")
    heldout_rms_per_sample_mg: float | None = Field(default=None, description="held-out RMS per sample, mg")


class ValueSigma(_Out):
    """A fitted parameter in physical units (its unit is in the parameter's name)."""

    value: float | None = Field(description="the value (null: not identifiable)")
    sigma: float | None = Field(default=None, description="its 1-sigma")
    identifiable: bool | None = Field(default=None, description="false: the data cannot give it")
    reason: str | None = Field(default=None, description="why not identifiable")
    test_to_identify: str | None = Field(default=None, description="what data would identify it")


class DutParameters(_Out):
    """One DUT's fitted parameters (station/diagnostics/report_values.py _params_json)."""

    baseline: dict[str, dict[str, ValueSigma]] = Field(
        default_factory=dict, description="parameter name (e.g. tdb_mg_per_c, acc0_g[o0]) -> axis -> value")
    effects: dict[str, dict[str, ValueSigma | dict[str, ValueSigma]]] = Field(
        default_factory=dict, description="effect -> parameter -> value (nonlinear) or axis -> value (linear)")


class LegsAgreement(_Out):
    """Do the held-out legs agree the effect generalises? (station/diagnostics/gate.py leg_agreement)"""

    legs_better: int | None = Field(default=None, description="held-out legs predicted better")
    legs: int | None = Field(default=None, description="held-out legs compared")
    heldout_loss_share: float | None = Field(default=None, description="what the legs predicted worse lose, as a "
                                             "share of what the better ones gain")
    legs_p: float | None = Field(default=None, description="one-sided sign-flip p of the legs' gains")


class GateRecord(LegsAgreement):
    """An admission test against the model before it (station/diagnostics/gate.py)."""

    effects: list[str] = Field(default_factory=list, description="the model it was tested against")
    heldout_rms_mg: float | None = Field(default=None, description="held-out RMS with the effect, mg")
    heldout_gain_rel: float | None = Field(default=None, description="relative held-out gain (0..1)")
    delta_bic: float | None = Field(default=None, description="delta BIC (negative: supported)")
    score: float | None = Field(default=None, description="likelihood-ratio statistic")
    score_df: int | None = Field(default=None, description="its degrees of freedom")
    score_p: float | None = Field(default=None, description="its p-value")
    at_bound: str | None = Field(default=None, description="its nonlinear parameters at a bound, in words")


class RankingEntry(LegsAgreement):
    """One candidate effect against the baseline (station/diagnostics/ranking.py)."""

    effect: str = Field(description="effect name (see library)")
    heldout_rms_mg: float | None = Field(default=None, description="held-out RMS with it, mg")
    rms_mg: float | None = Field(default=None, description="in-sample RMS with it, mg")
    heldout_gain_mg: float | None = Field(default=None, description="held-out RMS gain over the baseline, mg")
    heldout_gain_rel: float | None = Field(default=None, description="the same, relative (0..1)")
    delta_bic: float | None = Field(default=None, description="delta BIC against the baseline")
    n_eff: int | None = Field(default=None, description="prewhitened block count")
    score: float | None = Field(default=None, description="likelihood-ratio statistic")
    score_df: int | None = Field(default=None, description="its degrees of freedom")
    score_p: float | None = Field(default=None, description="its p-value")
    predicted_rms_reduction_mg: float | None = Field(default=None, description="in-sample RMS reduction, mg")
    evidence: bool = Field(default=False, description="it passes the admission gate on its own")
    admitted: bool = Field(default=False, description="the forward staircase admitted it")
    flags: list[str] = Field(default_factory=list, description="no_evidence, confusable_with:..., masked:..., "
                             "stands_for_it:..., explained_by:..., at_bound:... (labels: the page shows flags_text)")
    flags_text: list[str] = Field(default_factory=list, description="each flag in words, in the order of flags "
                                  "(web/diag_plots.py report_json; station/diagnostics/plots.py flag_words)")
    note: str | None = Field(default=None, description="what the effect is")
    shape: str | None = Field(default=None, description="its fitted shape in words")
    why: str | None = Field(default=None, description="why it was not admitted")
    term: str | None = Field(default=None, description="aliased effects: the shared term")
    aliases: list[str] | None = Field(default=None, description="effects identical to it on this data")
    same_as: str | None = Field(default=None, description="the alias in words")
    given_admitted: GateRecord | None = Field(default=None, description="its test against the admitted model")


class StaircaseStep(ModelFigures):
    """One model of a staircase: the baseline, then one more effect each step."""

    model: str = Field(description="'baseline' or '+effect'")
    effects: list[str] = Field(default_factory=list, description="the model's effects")
    parameters: dict[str, DutParameters] | None = Field(default=None, description="per serial (added steps only)")
    shape: str | None = Field(default=None, description="the added effect's shape in words")
    warning: str | None = Field(default=None, description="the added effect is not identifiable or aliased")
    delta_bic: float | None = Field(default=None, description="admitted staircase: its delta BIC")
    score_p: float | None = Field(default=None, description="admitted staircase: its p-value")


class Confusable(_Out):
    effects: list[str] = Field(description="the pair")
    cosine: float | None = Field(default=None, description="cosine of their fitted contributions")
    reason: str = Field(default="", description="why they are confusable")
    to_separate: str = Field(default="", description="what data would tell them apart")


class Unidentifiable(_Out):
    effect: str = Field(description="effect name")
    relative_residual_norm: float | None = Field(default=None, description="how far its regressors leave the "
                                                 "baseline's span (0: not at all)")
    reason: str = Field(default="", description="why it cannot be identified")
    needs: str | None = Field(default=None, description="what it needs")
    test_to_identify: str | None = Field(default=None, description="what data would identify it")


class AliasGroup(_Out):
    term: str = Field(description="the shared term")
    effects: list[str] = Field(description="effects with identical regressors on this data")
    ranked_as: str = Field(description="the name it is ranked under")
    text: str = Field(default="", description="in words")
    reason: str = Field(default="", description="why")


class DataFeatures(_Out):
    ramp_rates: bool | None = Field(default=None, description="the log has distinct ramp rates")
    ramp_rates_c_per_min: list[float | None] = Field(default_factory=list, description="ramp rates seen, C/min")
    orientations: int | None = Field(default=None, description="orientations logged")


class ArNoise(_Out):
    """The residual's noise model of one DUT and axis (station/diagnostics/noise_gls.py)."""

    model: str | None = Field(default=None, description="the model in words")
    theta: float | None = Field(default=None, description="IMA(1,1) theta (1: no random walk)")
    ar_order: int | None = Field(default=None, description="AR order p")
    phi: list[float] = Field(default_factory=list, description="AR coefficients")
    innovation_mg: float | None = Field(default=None, description="innovation sigma, mg")
    random_walk: bool | None = Field(default=None, description="a bias random walk is present")
    long_run_factor: float | None = Field(default=None, description="long-run variance factor")


class NoiseModelDoc(_Out):
    residual: str | None = Field(default=None, description="the noise model in words")
    baseline: dict[str, dict[str, ArNoise]] = Field(default_factory=dict, description="serial -> axis -> model")
    heldout: str | None = Field(default=None, description="the held-out scheme in words")


class DriftIdentifiability(_Out):
    tdsf_identifiable: dict[str, PerAxisBool] = Field(default_factory=dict, description="serial -> per axis")
    test_to_identify: str | None = Field(default=None, description="what data would identify TDSF")


class NonlinearParam(_Out):
    name: str = Field(description="parameter name")
    unit: str = Field(default="", description="its unit")


class EffectInfo(_Out):
    """One effect of the library (station/diagnostics/effects.py Effect.describe)."""

    effect: str = Field(description="effect name (the add= value)")
    note: str | None = Field(default=None, description="what it is")
    needs: str | None = Field(default=None, description="what data it needs")
    linear: list[str] = Field(default_factory=list, description="its linear parameters")
    nonlinear: list[NonlinearParam] = Field(default_factory=list, description="its nonlinear parameters")


class LeftoverView(_Out):
    """One view of the held-out residual (station/diagnostics/leftover.py VIEWS)."""

    view: str = Field(description="temperature, rate, time or orientation")
    plot: str | None = Field(default=None, description="the plot that shows it (.../diagnosis/{plot}.png)")
    text: str | None = Field(default=None, description="the view in words")
    excess_share: float | None = Field(default=None, description="share of the residual's variance its groups "
                                       "explain beyond what they explain of the noise (0..1)")


class LeftoverAxis(_Out):
    """One DUT axis: its held-out error against what the noise model expects on the same legs."""

    heldout_rms_mg: float | None = Field(default=None, description="held-out RMS, mg")
    expected_rms_mg: float | None = Field(default=None, description="what the noise alone would give, mg")
    expected_hi_rms_mg: float | None = Field(default=None, description="the upper quantile of that, mg")
    ratio: float | None = Field(default=None, description="held-out / expected")
    above: bool | None = Field(default=None, description="a residual remains on this axis")
    views_excess_share: dict[str, float | None] = Field(default_factory=dict, description="view -> excess share")
    follows: list[str] = Field(default_factory=list, description="views of temperature, rate or orientation the "
                               "residual follows more than every noise draw does")


class Leftover(_Out):
    """Is anything left that the model misses? (station/diagnostics/leftover.py): said first on the page."""

    statement: str | None = Field(default=None, description="the answer in words")
    above_floor: bool | None = Field(default=None, description="a residual remains above the noise")
    model: list[str] = Field(default_factory=list, description="the effects of the model it is about")
    heldout_rms_mg: float | None = Field(default=None, description="held-out RMS, mg")
    expected_rms_mg: float | None = Field(default=None, description="what the noise alone would give, mg")
    ratio: float | None = Field(default=None, description="held-out / expected")
    above: list[str] = Field(default_factory=list, description="the axes (serial axis) where a residual remains")
    views: list[LeftoverView] = Field(default_factory=list, description="the views, most telling first")
    carrying: list[str] = Field(default_factory=list, description="plots of the views that carry the structure")
    per_dut: dict[str, dict[str, LeftoverAxis]] = Field(default_factory=dict, description="serial -> axis -> figures")
    method: str | None = Field(default=None, description="how it is computed")


class OrientationName(_Out):
    """An orientation of a DUT's log as the CLI names it."""

    label: str = Field(description="the log's position index (or o0, o1, ... for orientations found by "
                       "clustering a log without a position column)")
    name: str = Field(description="'position 0 (P)', or 'orientation o0'")


class DiagnosisModel(ModelFigures):
    effects: list[str] = Field(default_factory=list, description="the model's effects (baseline + add=)")
    parameters: dict[str, DutParameters] = Field(default_factory=dict, description="per serial")


class DiagnosisOut(_Out):
    """Model diagnostics of one run (design 5.2, design 7)."""

    serials: list[str] = Field(description="the DUTs diagnosed")
    leftover: Leftover | None = Field(default=None, description="what the model leaves unexplained, in words first")
    orientations: dict[str, list[OrientationName]] = Field(default_factory=dict,
                                                           description="serial -> its orientations, named")
    residual: str = Field(description="what the residual is, with its unit")
    rms_basis: str = Field(description="what the RMS figures average over")
    baseline: ModelFigures = Field(description="the baseline model (TDB/TDSF)")
    ranking: list[RankingEntry] = Field(default_factory=list, description="candidate effects, best held-out first")
    model: DiagnosisModel = Field(description="the model with the added effects")
    staircase: list[StaircaseStep] = Field(default_factory=list, description="baseline, then each add= effect")
    confusable: list[Confusable] = Field(default_factory=list, description="pairs only other data separate")
    unidentifiable: list[Unidentifiable] = Field(default_factory=list, description="effects this data cannot identify")
    data_features: DataFeatures = Field(description="what the log holds")
    admitted: list[str] = Field(default_factory=list, description="effects the forward staircase admits")
    admitted_staircase: list[StaircaseStep] = Field(default_factory=list, description="that staircase")
    aliases: list[AliasGroup] = Field(default_factory=list, description="effects identical on this data")
    noise_model: NoiseModelDoc = Field(description="the residual's noise model")
    drift: DriftIdentifiability = Field(description="whether TDSF is identifiable")
    baseline_parameters: dict[str, DutParameters] = Field(default_factory=dict, description="per serial")
    plots: list[str] = Field(default_factory=list, description="plot names for .../diagnosis/{plot}.png, "
                             "in the page's order")
    library: list[EffectInfo] = Field(default_factory=list, description="every effect that can be added")
    noise: dict[str, dict[str, Any]] = free_form(
        "serial -> the residual's Allan-deviation noise view against the sensor's own noise "
        "(station/diagnostics/noise_view.py noise_view: per axis the residual, static and model-noise curves, "
        "noise terms and the comparison): the data of the Allan plot")


class DiagnosticModelOut(_Out):
    """The fitted model as a file (station/diagnostics/model.py DiagnosticModel.to_json)."""

    format: str = Field(description="file format tag")
    version: int = Field(description="model version")
    serial: str = Field(description="the DUT")
    t_ref_c: float = Field(description="reference temperature, C")
    t_power_on_s: float = Field(description="board time of power-on, s")
    effects: list[str] = Field(description="effects of the model")
    axes: dict[str, dict[str, float | None]] = Field(description="axis -> parameter -> value (units in the names)")
    nonlinear: dict[str, dict[str, float | None]] = Field(description="effect -> nonlinear parameter -> value")
    sigma: dict[str, dict[str, float | None | dict[str, float | None]]] = Field(
        description="1-sigma: axis -> parameter, and 'nonlinear' -> effect -> parameter")
