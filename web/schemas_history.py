"""Response models of the stored history: DUTs, runs, segments, the MES results feed, its webhook
and outbox, yields (db/repository.py through web/db_repo.py; web/views.py dut_view).
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import Field

from web.schemas_common import (
    SFEM_HELP, CheckOut, DecisionFields, StoredDecision, ThermalAxes, ThermalByMethod, ThermalRow, TraceFields,
    ProgramVerifyOut, _Out, free_form, one_of,
)
from web.schemas_thermal import SegmentRecord

REVISION_HELP = ("1 for a run's first final verdict; N + 1 for a later verdict of the same run that supersedes "
                 "revision N (a resumed batch judged again, a re-judge). Keep the latest revision per run_id")
SUPERSEDES_HELP = "idempotency_key of the record this one replaces; null for revision 1"
THERMAL_HELP = "the station's chosen result per axis x/y/z: TDB (mg/C) and TDSF (ppm/C) with their 1-sigma"



ROUTE_OUTCOMES = ("allowed", "refused", "unanswered")
ROUTE_CHECK_HELP = ("the MES's route check before the part was tested (design 5.4): 'allowed'; 'refused' (never "
                    "tested, attempt 0); 'unanswered' (no usable answer: tested only under the site's policy "
                    "proceed_and_flag, else stopped); null: no route check was asked")

class Identity(_Out):
    """What the board reported of itself (station/daemon/slots.py IDENTITY_FIELDS)."""

    serial: str | None = Field(default=None, description="the board's serial")
    sensor: str | None = Field(default=None, description="sensor type, e.g. LIS3DSH")
    fw: str | None = Field(default=None, description="firmware version ('' when not reported)")
    ug_per_lsb: float | None = Field(default=None, description="acceleration resolution, ug per LSB")
    t_lsb_per_c: float | None = Field(default=None, description="temperature LSB per C")
    t_lsb_at_25c: float | None = Field(default=None, description="temperature reading at 25 C, LSB")
    odr_hz: float | None = Field(default=None, description="output data rate, Hz")


class VerdictDetail(_Out):
    """The decision as stored with the run: every check (station/decisions/verdicts.py Verdict.to_json,
    with attempt and run_id; a record written by other means may carry fewer fields)."""

    verdict: str | None = Field(default=None, description="pass | marginal | fail | error")
    grade: str | None = Field(default=None, description="bin")
    tray: str | None = Field(default=None, description="tray")
    reason: str | None = Field(default=None, description="one line")
    reasons: list[str] | None = Field(default=None, description="every reason, worst first")
    failures: list[CheckOut] | None = Field(default=None, description="the checks that did not pass")
    checks: list[CheckOut] | None = Field(default=None, description="every check: measurement, axis, value, sigma, "
                                          "unit, low, high, outcome, reason")
    product: str | None = Field(default=None, description="the product judged as")
    limits_name: str | None = Field(default=None, description="limits set")
    limits_version: str | None = Field(default=None, description="its version")
    attempt: int | None = Field(default=None, description="the serial's attempt number")
    run_id: int | None = Field(default=None, description="the run judged")


class _Results(_Out):
    """A run's results (db/repository.py _run_results): thermal per method, SFEM, program and verify."""

    thermal: ThermalAxes | None = Field(default=None, description=THERMAL_HELP)
    thermal_method: str | None = Field(default=None, description="which method `thermal` comes from (offline "
                                       "preferred, else streaming)")
    thermal_by_method: ThermalByMethod = Field(default_factory=ThermalByMethod, description="every stored "
                                               "method's latest result")
    streaming: ThermalRow | None = Field(default=None, description="the streaming algorithm's stored result")
    offline: ThermalRow | None = Field(default=None, description="the offline fit's stored result")
    sfem: dict[str, Any] | None = free_form(SFEM_HELP, default=None)
    program_verify: ProgramVerifyOut | None = Field(default=None, description="program and verify: programmed, crc, "
                                                    "comp_on, verified, e_before_mg, e_after_mg, flags")


class DutOut(_Results, StoredDecision):
    """A DUT with the results of its result run: its latest valid attempt (db/repository.py dut_by_serial)."""

    serial: str = Field(description="the board's serial")
    sensor: str | None = Field(default=None, description="sensor type")
    first_seen: str | None = Field(default=None, description="first tested (ISO 8601 UTC)")
    last_seen: str | None = Field(default=None, description="last tested (ISO 8601 UTC)")
    n_runs: int | None = Field(default=None, description="runs of real parts (replays not counted)")
    attempts: int | None = Field(default=None, description="attempts at this serial: its runs that tested the part "
                                 "(a run stopped for a label mismatch is in n_runs, not here)")
    result_run_id: int | None = Field(default=None, description="the run the results come from")
    run_id: int | None = Field(default=None, description="the same run (latest valid attempt, else latest with results)")
    batch_id: int | None = Field(default=None, description="that run's batch")
    finished_at: str | None = Field(default=None, description="when that run ended (ISO 8601 UTC)")


class DutSummary(_Out):
    serial: str = Field(description="the board's serial")
    sensor: str | None = Field(default=None, description="sensor type")
    runs: int = Field(default=0, description="runs of this serial")
    last_run_id: int | None = Field(default=None, description="its latest run")
    last_state: str | None = Field(default=None, description="that run's state")
    last_at: str | None = Field(default=None, description="when it was last seen (ISO 8601 UTC)")


class RunOut(_Results, StoredDecision, TraceFields):
    """One DUT run with its results (db/repository.py run_detail)."""

    id: int = Field(description="run id")
    station: str | None = Field(default=None, description="the station that measured it (config `name`)")
    batch_id: int | None = Field(default=None, description="its batch")
    slot: str | None = Field(default=None, description="its slot")
    serial: str | None = Field(default=None, description="the board's serial")
    label_serial: str | None = Field(default=None, description="serial scanned from the part's label, if any")
    route_check: str | None = one_of(ROUTE_OUTCOMES, ROUTE_CHECK_HELP, default=None)
    route_reason: str | None = Field(default=None, description="the MES's words (refused, allowed) or what went wrong "
                                     "(unanswered); '' when none")
    sensor: str | None = Field(default=None, description="not sent at present (always null): see identity.sensor")
    identity: Identity | None = Field(default=None, description="what the board reported of itself")
    software_version: str | None = Field(default=None, description="the station software's version that measured it "
                                         "(null: not stored, a run from before schema 0009)")
    firmware_version: str | None = Field(default=None, description="the board firmware's version, as its identity "
                                         "reply reported it (null: the board reports none, or not stored)")
    holder: str | None = one_of(("fixture", "operator"), "what turned the plate: 'fixture' (the motorized fixture) "
                                "or 'operator' (a person turned it by hand); null: not stored", default=None)
    profile: str | None = Field(default=None, description="its batch's profile")
    operator: str | None = Field(default=None, description="its batch's operator")
    state: str | None = Field(default=None, description="connecting, running, done, faulted, interrupted")
    fault_reason: str | None = Field(default=None, description="why it faulted ('' when it did not)")
    n_samples: int | None = Field(default=None, description="samples stored")
    lost_samples: int | None = Field(default=None, description="samples lost on the link")
    samples_pruned_at: str | None = Field(default=None, description="when its raw samples were pruned (ISO 8601 "
                                          "UTC); null while kept")
    n_segments: int | None = Field(default=None, description="segments logged")
    result_seq: int | None = Field(default=None, description="the MES cursor of its current verdict record")
    started_at: str | None = Field(default=None, description="ISO 8601 UTC")
    ended_at: str | None = Field(default=None, description="ISO 8601 UTC; null while running")
    finished_at: str | None = Field(default=None, description="the same as ended_at")
    verdict_detail: VerdictDetail | None = Field(
        default=None, description="the decision with every check (measurement, axis, value, sigma, low, high, "
        "outcome, reason)")
    fault_code: str | None = Field(default=None, description="the machine code of `fault_reason` "
                                   "(station/records/causes.py reason_code, e.g. "
                                   "'link_lost'); null when no rule names the words")

    words_codes: ClassVar[dict[str, str]] = {**StoredDecision.words_codes, "fault_code": "fault_reason"}


class SegmentOut(SegmentRecord):
    """One stored segment (db/repository.py segment_json): the segment plus its row, run and step."""

    id: int | None = Field(default=None, description="segment row id")
    run_id: int | None = Field(default=None, description="its run")
    step_index: int | None = Field(default=None, description="the profile step it was logged in")
    created_at: str | None = Field(default=None, description="when stored (ISO 8601 UTC)")


class ResultOut(_Results, StoredDecision, TraceFields):
    """One MES record: a run's final verdict with its results (design 8; db/repository.py results_since)."""

    id: int = Field(description="the record's cursor (result_seq), increasing in commit order")
    idempotency_key: str = Field(description="the record's key; the webhook sends the same")
    revision: int | None = Field(default=None, description=REVISION_HELP)
    supersedes: str | None = Field(default=None, description=SUPERSEDES_HELP)
    serial: str = Field(description="the board's serial")
    label_serial: str | None = Field(default=None, description="serial scanned from the part's label, if any")
    route_check: str | None = one_of(ROUTE_OUTCOMES, ROUTE_CHECK_HELP, default=None)
    route_reason: str | None = Field(default=None, description="the MES's words (refused, allowed) or what went wrong "
                                     "(unanswered); '' when none")
    sensor: str | None = Field(default=None, description="sensor type")
    run_id: int | None = Field(default=None, description="the run judged")
    batch_id: int | None = Field(default=None, description="its batch")
    station: str | None = Field(default=None, description="the station that measured it (config `name`)")
    slot: str | None = Field(default=None, description="its slot")
    profile: str | None = Field(default=None, description="its batch's profile")
    operator: str | None = Field(default=None, description="its batch's operator")
    state: str | None = Field(default=None, description="the run's end state")
    created_at: str | None = Field(default=None, description="when the record was stored (ISO 8601 UTC)")
    ended_at: str | None = Field(default=None, description="when the run ended (ISO 8601 UTC)")


class ResultsPage(_Out):
    results: list[ResultOut] = Field(description="the records of this page, in increasing id")
    next: str = Field(description="cursor to go on with (pass as since=), never null: the last id of this page, or, "
                      "when the page is empty, the since that was given ('0' when none). Poll with it: each "
                      "record is read once")


class MesResultPayload(DecisionFields, TraceFields):
    """The body of each MES webhook POST (one per verdict record: a run's final verdict, and each
    later one that supersedes it; the same Idempotency-Key header on every retry)."""

    idempotency_key: str = Field(description="the record's key (also the Idempotency-Key header)")
    station: str = Field(description="the station that measured it")
    result_id: int | None = Field(default=None, description="the results feed cursor of this record")
    revision: int | None = Field(default=None, description=REVISION_HELP)
    supersedes: str | None = Field(default=None, description=SUPERSEDES_HELP)
    serial: str = Field(description="the board's serial")
    run_id: int | None = Field(default=None, description="the run judged")
    batch_id: int | None = Field(default=None, description="its batch")
    slot: str | None = Field(default=None, description="its slot")
    created_at: str | None = Field(default=None, description="when the record was stored (ISO 8601 UTC)")
    thermal: ThermalAxes | None = Field(default=None, description=THERMAL_HELP)
    streaming: ThermalRow | None = Field(default=None, description="the streaming fit's result (null when none)")
    offline: ThermalRow | None = Field(default=None, description="the offline fit's result (null when none)")
    sfem: dict[str, Any] | None = free_form(SFEM_HELP, default=None)
    profile: str | None = Field(default=None, description="its batch's profile")
    operator: str | None = Field(default=None, description="its batch's operator (the person)")
    sensor: str | None = Field(default=None, description="sensor type")
    label_serial: str | None = Field(default=None, description="serial scanned from the part's label, if any")
    route_check: str | None = one_of(ROUTE_OUTCOMES, ROUTE_CHECK_HELP, default=None)
    route_reason: str | None = Field(default=None, description="the MES's words (refused, allowed) or what went wrong "
                                     "(unanswered); '' when none")


class OutboxEntry(_Out):
    """One queued MES webhook delivery (db/repository.py outbox_json, without its payload)."""

    id: int | None = Field(default=None, description="outbox row id")
    idempotency_key: str = Field(description="the record's key")
    topic: str | None = Field(default=None, description="what it carries (result)")
    state: str | None = Field(default=None, description="pending or delivered")
    attempts: int = Field(default=0, description="delivery attempts made")
    next_attempt_at: str | None = Field(default=None, description="when it is tried next (ISO 8601 UTC)")
    delivered_at: str | None = Field(default=None, description="when the MES accepted it; null while pending")
    last_error: str | None = Field(default=None, description="the last attempt's error ('' when none)")
    created_at: str | None = Field(default=None, description="when queued (ISO 8601 UTC)")


class YieldOut(_Out):
    batch_id: int | None = Field(default=None, description="the batch asked for (null: every batch)")
    duts: int = Field(description="DUTs judged at least once")
    attempts: int = Field(description="judged attempts of those DUTs")
    retested: int = Field(description="DUTs with more than one judged attempt")
    first_pass: int = Field(description="DUTs whose first judged attempt passed")
    final_pass: int = Field(description="DUTs whose latest valid (non-error) attempt passed")
    first_pass_yield: float | None = Field(description="first_pass / duts (0..1); null without DUTs")
    final_yield: float | None = Field(description="final_pass / duts (0..1); null without DUTs")

