"""Response models of the records routes (web/routes/records.py): the audit trail, replays, and
yield / SPC / failure Pareto (station/records/spc.py, pareto.py). Moved out of web/schemas.py
(which re-exports the old names) so the records view can grow without touching the models
everyone else edits.

Policy of web/schemas.py: extra fields pass at runtime (`_Out`, forward compatible), but every
field a route sends is declared, typed and described here, so a client generated from
/openapi.json sees all of it (tests/test_openapi_truth.py holds the routes to it).
"""

from __future__ import annotations

from pydantic import ConfigDict, Field

from web.schemas_common import _Out, free_form


class AuditEntry(_Out):
    """One audited action (db.repository.audit_list)."""

    id: int = Field(description="row id, increasing (page back with before_id)")
    at: str = Field(description="when (UTC, ISO 8601)")
    station: str = Field(description="the station that handled the request (config `name`)")
    actor: str = Field(description="the token's name (never the token)")
    action: str = Field(description="batch.start | batch.abort | prompt.answer | batch.resume | limits.change | "
                        "verdict superseded")
    target: str = Field(description="what it acted on, e.g. 'batch 12'")
    detail: dict = free_form("what the request carried; its keys depend on the action (e.g. profile, slots, "
                             "operator for batch.start)", default_factory=dict)


class VerdictChangeOut(_Out):
    """A DUT whose verdict the replay changed."""

    serial: str = Field(description="the DUT")
    before: str | None = Field(default=None, description="verdict in the recording")
    after: str | None = Field(default=None, description="verdict of the replay")


class ChangeOut(_Out):
    """One number or word of a DUT's outcome that differs (station/replay/compare.py Change)."""

    key: str = Field(description="what, e.g. 'offline.x.tdb_mg_per_c', 'verdict'")
    before: float | str | None = Field(default=None, description="in the recording (number in the key's unit, or word)")
    after: float | str | None = Field(default=None, description="in the replay")
    delta: float | None = Field(default=None, description="after - before, for numbers")


class LargestChangeOut(ChangeOut):
    """The largest relative change of a number in the replay, and whose."""

    serial: str = Field(description="the DUT")


class ReplaySummary(_Out):
    """How many DUTs the replay changed (station/replay/compare.py ReplayDiff.summary)."""

    duts: int = Field(default=0, description="DUTs compared")
    unchanged: int = Field(default=0, description="DUTs whose every number and word is within tolerance")
    changed: int = Field(default=0, description="DUTs with a change (or different samples)")
    verdicts_changed: list[VerdictChangeOut] = Field(default=[], description="DUTs whose verdict changed")
    largest_change: LargestChangeOut | None = Field(default=None, description="null: no number changed")


class EpisodeOut(_Out):
    """A disagreement of the plate longer than the window (station/replay/agreement.py)."""

    from_s: float = Field(description="start, sample time (s)")
    to_s: float = Field(description="end, sample time (s)")
    duration_s: float = Field(description="seconds")
    replay: int = Field(description="the replay's state (lamp 0/1, fixture position)")
    recorded: int = Field(description="the recording's state")


class PlateSideOut(_Out):
    """Lamp or fixture of the replay against the recording."""

    checked_s: float = Field(description="sample seconds compared")
    disagree_s: float = Field(description="sample seconds they disagreed (latency included)")
    agrees: bool = Field(description="no disagreement longer than the window")
    episodes: list[EpisodeOut] = Field(default_factory=list, description="disagreements longer than the window")


class PlateAgreementOut(_Out):
    """Did the replayed plate do what the recorded one did (station/replay/agreement.py)."""

    agrees: bool | None = Field(default=None, description="lamp and fixture agreed (null: not comparable)")
    window_s: float | None = Field(default=None, description="disagreements up to this long are command latency")
    note: str | None = Field(default=None, description="why it could not be compared")
    samples: int | None = Field(default=None, description="samples both have")
    lamp: PlateSideOut | None = Field(default=None, description="the lamp")
    fixture: PlateSideOut | None = Field(default=None, description="the fixture position")


class DutDiffOut(_Out):
    """One DUT of a replay against its recording (station/replay/compare.py DutDiff)."""

    slot: str = Field(description="slot of the replay")
    serial: str = Field(description="the DUT")
    changed: bool = Field(description="any change, or samples not identical")
    compared: int = Field(description="numbers and words compared")
    samples_identical: bool | None = Field(default=None, description="what the board sent = the recording, "
                                           "in counts (null: not compared)")
    note: str = Field(default="", description="e.g. 'no replayed run'")
    changes: list[ChangeOut] = Field(default_factory=list, description="every changed number and word")


class ReplayDiffOut(_Out):
    """A replay's comparison with its recording (station/replay/compare.py ReplayDiff.to_json)."""

    source: str = Field(default="", description="what was replayed")
    before: str = Field(default="", description="what 'before' is: the recording's label")
    rtol: float | None = Field(default=None, description="relative tolerance of a number")
    atol: float | None = Field(default=None, description="absolute tolerance of a number")
    replay_batch_id: int | None = Field(default=None, description="the replay batch")
    replay_state: str | None = Field(default=None, description="how the replay batch ended")
    replay_error: str | None = Field(default=None, description="why it failed, if it did")
    recorded_state: str | None = Field(default=None, description="how the recorded batch ended")
    ended_at_recording_end: bool | None = Field(default=None, description="the replay stopped where the recording "
                                                "of an unfinished batch ends")
    end_changed: bool | None = Field(default=None, description="the batch ended otherwise than the recorded one")
    notes: list[str] = Field(default_factory=list, description="what the replay did for the recorded line")
    summary: ReplaySummary | None = Field(default=None, description="counts")
    agreement: PlateAgreementOut | None = Field(default=None, description="lamp and fixture against the recording")
    duts: list[DutDiffOut] = Field(default_factory=list, description="per DUT")


class ReplayEntry(_Out):
    """A replay batch (station replay): recorded data re-run through the station, never sent to the MES."""

    batch_id: int = Field(description="the replay batch")
    station: str = Field(default="", description="station that ran it")
    profile: str = Field(default="", description="profile it ran")
    state: str = Field(default="", description="batch state (running, finished, ...)")
    replay_of: str = Field(description="the source: 'batch 12 of line-A (...)' or '3 CSV logs'")
    created_at: str | None = Field(default=None, description="started (UTC, ISO 8601)")
    ended_at: str | None = Field(default=None, description="ended (UTC, ISO 8601; null while it runs)")
    summary: ReplaySummary | None = Field(default=None, description="null while the replay runs")
    plate_agrees: bool | None = Field(default=None, description="lamp and fixture agreed with the recording")


class ReplayOut(_Out):
    """One replay's comparison with the recording."""

    batch_id: int = Field(description="the replay batch")
    replay_of: str = Field(description="the source")
    state: str = Field(default="", description="batch state")
    created_at: str | None = Field(default=None, description="started (UTC, ISO 8601)")
    diff: ReplayDiffOut | None = Field(default=None, description="null while the replay runs")


class SpcFlagOut(_Out):
    rule: str = Field(description="'1'..'8' (Nelson / Western Electric run rule) or 'MR' (moving range above D4 x MR-bar)")
    name: str = Field(description="the rule in words, e.g. '9 in a row on one side of the centre line'")


class SpcPointOut(_Out):
    """One judged run's value of the parameter, judged by its OWN run's limits."""

    index: int = Field(description="1-based run index in the chart (the x axis)")
    run_id: int = Field(description="the DUT run")
    batch_id: int = Field(description="its batch")
    station: str = Field(default="", description="station that judged it")
    slot: str = Field(default="", description="slot it was tested in")
    serial: str = Field(default="", description="the DUT's serial")
    work_order: str = Field(default="", description="the batch's work order ('' = not given)")
    at: str | None = Field(default=None, description="judged at, UTC 'YYYY-MM-DDTHH:MM:SSZ'")
    value: float = Field(description="the parameter's value, in the check's unit (`unit`)")
    low: float | None = Field(default=None, description="LSL of this run's own limits (null: none)")
    high: float | None = Field(default=None, description="USL of this run's own limits (null: none)")
    verdict: str | None = Field(default=None, description="the run's verdict")
    outcome: str | None = Field(default=None, description="this check's outcome as the station judged it "
                                "(guard band included): pass, marginal, fail, error")
    spec: str = Field(description="'in spec', 'above USL' or 'below LSL': the value against its own limits")
    out_of_spec: bool = Field(description="spec != 'in spec'")
    flags: list[SpcFlagOut] = Field(default_factory=list, description="run rules and MR flag that name this point")


class SpcGroupOut(_Out):
    """Product x limits version: a chart never mixes two."""

    key: str = Field(description="opaque; send it back as `group=`")
    product: str = Field(description="part number and revision of the batches ('' = unspecified product)")
    limits_name: str = Field(default="", description="limits set the runs were judged by")
    limits_version: str = Field(default="", description="its version")
    label: str = Field(description="e.g. 'LIS3DSH-01 rev B · LIS3DSH v3'")
    runs: int = Field(description="judged runs of the group under the filters")
    last_at: str | None = Field(default=None, description="newest judging time in the group (UTC)")


class SpcChartOut(_Out):
    """Individuals / moving-range chart of the group (station/records/spc.py IChart)."""

    n: int = Field(default=0, description="points")
    mean: float | None = Field(default=None, description="centre line")
    mr_bar: float | None = Field(default=None, description="mean moving range |x[i] - x[i-1]|")
    sigma_within: float | None = Field(default=None, description="MR-bar / 1.128")
    ucl: float | None = Field(default=None, description="mean + 3 sigma_within")
    lcl: float | None = Field(default=None, description="mean - 3 sigma_within")
    mr_ucl: float | None = Field(default=None, description="3.267 MR-bar")
    moving_ranges: list[float] = Field(default_factory=list, description="|x[i] - x[i-1]|, i = 1..n-1")
    out_of_control: list[int] = Field(default_factory=list, description="0-based indices beyond the control limits (rule 1)")
    flagged: list[int] = Field(default_factory=list, description="0-based indices with any rule or MR flag")
    rule_counts: dict[str, int] = Field(default_factory=dict, description="points flagged per rule code")


class SpcCapabilityOut(_Out):
    """Capability of the group against its one set of limits (station/records/spc.py Capability)."""

    n: int = Field(default=0, description="points")
    min_n: int = Field(description="Cpk and Ppk are computed from n >= min_n only")
    low: float | None = Field(default=None, description="the group's LSL (null: none, or the limits differ)")
    high: float | None = Field(default=None, description="the group's USL")
    mean: float | None = Field(default=None, description="mean of the points")
    sigma_within: float | None = Field(default=None, description="MR-bar / 1.128 (short-term sigma Cpk uses)")
    sigma_overall: float | None = Field(default=None, description="sample standard deviation")
    cpk: float | None = Field(default=None, description="null below min_n or without one set of limits (see reason)")
    ppk: float | None = Field(default=None, description="as cpk with sigma_overall (null below min_n)")
    cpk_ci_low: float | None = Field(default=None, description="Bissell normal-approximation interval, ci_level")
    cpk_ci_high: float | None = Field(default=None, description="upper end of the interval")
    ci_level: float = Field(default=0.95, description="confidence level of the interval")
    target: float = Field(default=1.33, description="Cpk below this is highlighted")
    below_target: bool | None = Field(default=None, description="cpk < target (null: no cpk)")
    reason: str | None = Field(default=None, description="why cpk is null, e.g. 'n=12 < 25'")
    out_of_spec: int = Field(default=0, description="points outside their OWN run's limits")


class HistogramOut(_Out):
    """Histogram of the group's values, bins spanning the data and its spec limits."""

    edges: list[float] = Field(default_factory=list, description="bin edges (n bins + 1), in the parameter's unit")
    counts: list[int] = Field(default_factory=list, description="points per bin")


class SlotTrendOut(_Out):
    """The group's values of one slot (a slot that reads high is a fixture or link problem)."""

    slot: str = Field(description="slot name")
    n: int = Field(description="points")
    mean: float | None = Field(default=None, description="their mean")
    values: list[float] = Field(default_factory=list, description="the values, oldest first")


class YieldRowOut(_Out):
    """Yield of one group of runs: pass / judged attempts, and first-pass and final yield of its
    DUTs by the rule of GET /api/yield."""

    key: str = Field(description="the batch id, day (UTC), product, limits set or station")
    judged: int = Field(description="judged runs (attempts; a label mismatch, attempt 0, is none)")
    passed: int = Field(description="verdict pass")
    marginal: int = Field(description="verdict marginal")
    failed: int = Field(description="verdict fail")
    errors: int = Field(description="verdict error")
    yield_pct: float | None = Field(default=None, description="100 * passed / judged (of the attempts)")
    duts: int = Field(default=0, description="DUTs with a judged attempt in the group")
    first_pass: int = Field(default=0, description="of them, DUTs whose first judged attempt passed")
    final_pass: int = Field(default=0, description="of them, DUTs whose latest valid (non-error) attempt passed")
    first_pass_pct: float | None = Field(default=None, description="first-pass yield, 100 * first_pass / duts "
                                         "(GET /api/yield first_pass_yield, in %)")
    final_pct: float | None = Field(default=None, description="final yield, 100 * final_pass / duts "
                                    "(GET /api/yield final_yield, in %)")


class FilterOption(_Out):
    """One choice of a filter select."""

    value: str = Field(description="what to send back as the filter ('(unspecified)' = runs without one)")
    label: str = Field(description="in words")
    runs: int = Field(description="judged runs in the date range")


class RecordsOptions(_Out):
    """The choices of the filter selects: from the runs in the date range, not narrowed by the other
    filters (choosing a product must not empty the product list)."""

    products: list[FilterOption] = Field(default_factory=list, description="part number + revision")
    stations: list[FilterOption] = Field(default_factory=list, description="stations")
    work_orders: list[FilterOption] = Field(default_factory=list, description="work orders")


class RecordsFilters(_Out):
    """The filters the answer was computed under, as understood."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    from_: str | None = Field(default=None, alias="from", description="first day (UTC, ISO date), inclusive")
    to: str | None = Field(default=None, description="last day (UTC, ISO date), inclusive")
    product: str | None = Field(default=None, description="product filter as given")
    station: str | None = Field(default=None, description="station filter")
    work_order: str | None = Field(default=None, description="work order filter")
    limit: int = Field(description="the newest N judged runs under the filters")


class SpcOut(_Out):
    """One chart: ONE parameter of ONE group (product x limits version), with the groups available
    under the filters, the yield tables and the filter choices."""

    parameter: str = Field(description="'measurement' or 'measurement:axis' ('' when nothing is judged)")
    label: str = Field(default="", description="in words with unit, e.g. 'TDB x (mg/°C)'")
    unit: str = Field(default="", description="as the checks carry it, e.g. 'mg/C'")
    parameters: list[str] = Field(default_factory=list, description="every judged measurement of the group with values")
    parameter_labels: dict[str, str] = Field(default_factory=dict, description="parameter -> words with unit")
    group: SpcGroupOut | None = Field(default=None, description="the group shown (null: no judged run)")
    groups: list[SpcGroupOut] = Field(default_factory=list, description="every group under the filters, newest first")
    rules: dict[str, str] = Field(default_factory=dict, description="rule code -> name, the legend of the flags")
    points: list[SpcPointOut] = Field(default_factory=list, description="oldest first")
    chart: SpcChartOut = Field(description="I-MR chart of the group")
    capability: SpcCapabilityOut = Field(description="Cpk, Ppk and out-of-spec count of the group")
    histogram: HistogramOut = Field(description="histogram of the group")
    slots: list[SlotTrendOut] = Field(default_factory=list, description="per slot: n, mean, values")
    yield_: dict[str, list[YieldRowOut]] = Field(default_factory=dict, alias="yield",
                                                 description="per batch, day (UTC), product, limits and station over "
                                                 "every run under the filters: judged, passed, marginal, failed, "
                                                 "errors, yield_pct; duts, first_pass, final_pass, first_pass_pct, "
                                                 "final_pct")
    columns: list[str] = Field(default_factory=list, description="the points table's columns = the CSV's header")
    filters: RecordsFilters = Field(description="the filters as understood")
    options: RecordsOptions = Field(description="the filter choices of the date range")


class ParetoRowOut(_Out):
    """One row of the failure Pareto (station/records/pareto.py ParetoRow)."""

    table: str = Field(description="'checks' (fail/error checks per parameter) or 'causes' (runs judged fail or error, "
                                   "one cause each)")
    rank: int = Field(description="1 = most frequent in its table")
    key: str = Field(description="parameter ('tdb_mg_per_c:x') or cause")
    what: str = Field(description="in words: 'TDB x' (checks); 'label mismatch', 'plate never arrived', 'link lost', "
                                  "'not measured', 'limit: TDB' (causes)")
    fail: int = Field(description="checks with outcome fail, or runs judged fail (causes)")
    error: int = Field(description="checks with outcome error, or runs judged error (causes)")
    count: int = Field(description="fail + error")
    pct: float = Field(description="of the table's total, rounded to 0.1")
    cum_pct: float = Field(description="cumulative, rounded to 0.1")
    example: str = Field(default="", description="one reason as the station wrote it (causes)")


class ParetoOut(_Out):
    """Which check fails most, and why runs do not pass, by cause (station/records/pareto.py, causes.py)."""

    runs: int = Field(description="judged runs under the filters")
    runs_failed: int = Field(description="of them, verdict fail")
    runs_error: int = Field(description="of them, verdict error")
    checks: list[ParetoRowOut] = Field(default_factory=list, description="most frequent first")
    causes: list[ParetoRowOut] = Field(default_factory=list, description="one per run judged fail or error, by "
                                       "name (station/records/causes.py), most frequent first")
    columns: list[str] = Field(default_factory=list, description="the table's columns = the CSV's header")
    filters: RecordsFilters = Field(description="the filters as understood")
    options: RecordsOptions = Field(description="the filter choices of the date range")
