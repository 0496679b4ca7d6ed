"""Pydantic models of the REST API (design 5.3): they validate input (422 with a message) and make
the OpenAPI document (/openapi.json, rendered at /docs) describe every route.

Response models allow extra fields so that the daemon and the database may add information without
breaking the contract; the fields named here are the ones clients may rely on.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

SLOT_PATTERN = r"^[A-Za-z0-9_.:\-/]{1,64}$"


class _Out(BaseModel):
    model_config = ConfigDict(extra="allow")


VerdictName = Literal["pass", "marginal", "fail", "error"]


class DecisionFields(_Out):
    """The station's decision on a DUT run (station/decisions/verdicts.py); null while it is not judged."""

    verdict: VerdictName | None = Field(
        default=None, description="pass | marginal (an uncertainty interval crosses a limit, or a value is in a "
        "marginal band) | fail | error (faulted, incomplete or not measured: never pass)")
    grade: str | None = Field(default=None, description="bin from the product's config: e.g. A, B; "
                              "'hold' for marginal, 'reject' for fail, 'retest' for error")
    tray: str | None = Field(default=None, description="where the operator puts the board")
    reason: str | None = Field(default=None, description="plain words, e.g. 'z TDSF -612 ppm/C, limit -500'")
    attempt: int | None = Field(default=None, description="the serial's attempt number (retest: 2, 3, ...)")
    limits_name: str | None = Field(default=None, description="limits set the DUT was judged by")
    limits_version: str | None = Field(default=None, description="version of that limits set")


class DecisionSummary(_Out):
    judged: int = 0
    verdicts: dict[str, int] = Field(default_factory=dict, description="count per verdict")
    grades: dict[str, int] = Field(default_factory=dict, description="count per grade")


class SortingEntry(_Out):
    slot: str
    serial: str | None = None
    verdict: VerdictName | None = None
    grade: str | None = None
    tray: str | None = None
    reason: str | None = None
    attempt: int | None = None


class TimeLeft(_Out):
    step_s: float | None = Field(default=None, description="sample seconds left in the step (estimate)")
    batch_s: float | None = Field(default=None, description="sample seconds left in the batch (estimate)")
    step_wall_s: float | None = Field(default=None, description="wall seconds left in the step")
    batch_wall_s: float | None = Field(default=None, description="wall seconds left in the batch")


class YieldOut(BaseModel):
    batch_id: int | None = None
    duts: int = Field(description="DUTs judged at least once")
    attempts: int
    retested: int = Field(description="DUTs with more than one judged attempt")
    first_pass: int = Field(description="DUTs whose first judged attempt passed")
    final_pass: int = Field(description="DUTs whose latest valid (non-error) attempt passed")
    first_pass_yield: float | None
    final_yield: float | None


class BatchCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    profile: str = Field(min_length=1, max_length=64, description="profile name, see GET /api/profiles")
    slots: list[Annotated[str, Field(min_length=1, max_length=64, pattern=r"\S")]] | None = Field(
        default=None, description="slots to test; null = every connected slot", min_length=1, max_length=1024
    )
    operator: str = Field(min_length=1, max_length=100, description="operator name or badge id")

    @model_validator(mode="before")
    @classmethod
    def _empty_slots(cls, data: Any) -> Any:
        """Before the schema's minItems, so the message says what null means."""
        if isinstance(data, dict) and data.get("slots") == []:
            raise ValueError("slots must be null (every slot) or a non-empty list of slot names")
        return data

    @field_validator("slots")
    @classmethod
    def _slots_ok(cls, v: list[str] | None) -> list[str] | None:
        if v is None:
            return v
        if not v:
            raise ValueError("slots must be null (every slot) or a non-empty list of slot names")
        if len(set(v)) != len(v):
            raise ValueError("slots must not repeat a slot")
        for s in v:
            if not isinstance(s, str) or not s.strip():
                raise ValueError("slot names must be non-empty strings")
        return v

    @field_validator("operator", "profile")
    @classmethod
    def _not_blank(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("must not be blank")
        return v.strip()


class BatchCreated(BaseModel):
    id: int


class StepInfo(_Out):
    index: int | None = None
    name: str | None = None
    count: int | None = Field(default=None, description="number of steps of the profile")


class SlotStatus(DecisionFields):
    slot: str
    serial: str | None = None
    state: str | None = None
    segments: int = Field(default=0, description="segments logged in this batch")
    error: str | None = Field(default=None, description="fault reason, when faulted")
    temp_c: float | None = None
    samples: int | None = None
    program: dict[str, Any] | None = Field(default=None, description="program and verify: written, read back "
                                           "(crc, readback_crc, readback_identical), comp, attempts, retries; or error_kind/error")
    verification: dict[str, Any] | None = Field(default=None, description="program and verify: passed, e_before_mg, "
                                                "e_after_mg per axis, flags (named residual drift), per-axis detail")
    run_id: int | None = Field(default=None, description="this DUT's run in this batch")
    plot_url: str | None = Field(default=None, description="the plot of THIS run (/api/runs/{run_id}/plot.png): "
                                 "never the serial's latest run, so an interrupted DUT shows its own data")
    steps_done: int = Field(default=0, description="profile steps this DUT completed (progress dots)")
    waiting_for: str | None = Field(default=None, description="what this DUT's current step waits for; "
                                    "'other DUTs' once it has what the step needs; null when not live")


class BatchStatus(_Out):
    id: int
    profile: str | None = None
    operator: str | None = None
    state: str
    step: StepInfo | None = None
    slots: list[SlotStatus] = []
    error: str | None = None
    prompt: dict[str, Any] | None = None
    lamp_on: bool | None = Field(default=None, description="what the station last commanded")
    lamp_state: Literal["on", "off", "unknown"] | None = Field(
        default=None, description="'unknown' while the lamp relay does not answer reads or writes")
    decision: DecisionSummary | None = Field(default=None, description="verdict and grade counts")
    sorting: list[SortingEntry] = Field(default=[], description="which slot goes to which tray")
    time_left: TimeLeft | None = None
    elapsed_s: float | None = Field(default=None, description="wall seconds since the batch started (to its end)")
    waiting_for: str | None = Field(
        default=None, description="what the current step waits for: boards, fixture, operator, chamber, "
        "temperature rise, static dwell, segment, dwell, programming, analysis; null once ended")
    ended_by: str | None = Field(default=None, description="who ended the batch: the token's name for an abort, "
                                 "'station' for an end it reached itself, 'daemon' for a shutdown; null while running")
    ended_at: str | None = Field(default=None, description="when the batch ended (RFC 3339 UTC); null while running")
    analysis: str | None = Field(default=None, description="the profile's analysis: thermal, sfem or none")
    note: str | None = Field(default=None, description="what the profile does not give, e.g. no calibration result "
                             "for analysis 'none' (validation)")
    counts: dict[str, int] | None = Field(default=None, description="DUTs per state: running (live), done, "
                                          "faulted, interrupted")


class Prompt(_Out):
    prompt_id: int
    text: str
    position: int | None = None


class PromptAnswer(BaseModel):
    model_config = ConfigDict(extra="forbid")

    prompt_id: int = Field(ge=0, description="the id of the prompt being answered (GET .../prompt)")
    answer: str = Field(default="done", min_length=1, max_length=64)


class Ack(BaseModel):
    ok: bool = True
    detail: str = ""


class AxisThermalOut(_Out):
    tdb_mg_per_c: float | None = None
    tdsf_ppm_per_c: float | None = None


class DutOut(DecisionFields):
    serial: str
    sensor: str | None = None
    run_id: int | None = Field(default=None, description="run the results come from (latest with results)")
    batch_id: int | None = None
    finished_at: str | None = None
    thermal: dict[str, AxisThermalOut] | None = Field(
        default=None, description="per axis x/y/z: TDB (mg/C) and TDSF (ppm/C), the station's chosen method"
    )
    streaming: dict[str, Any] | None = Field(default=None, description="streaming algorithm result")
    offline: dict[str, Any] | None = Field(default=None, description="offline fit result")
    sfem: dict[str, Any] | None = None
    program_verify: dict[str, Any] | None = Field(default=None, description="latest run's program and verify: "
                                                  "programmed, crc, comp_on, verified, e_before_mg, e_after_mg, flags")


class DutSummary(_Out):
    serial: str
    sensor: str | None = None
    runs: int = 0
    last_run_id: int | None = None
    last_state: str | None = None
    last_at: str | None = None


class RunOut(DecisionFields):
    id: int
    station: str | None = None
    verdict_detail: dict[str, Any] | None = Field(
        default=None, description="the decision with every check (measurement, axis, value, sigma, low, high, "
        "outcome, reason)")
    batch_id: int | None = None
    slot: str | None = None
    serial: str | None = None
    sensor: str | None = None
    profile: str | None = None
    state: str | None = None
    fault_reason: str | None = None
    started_at: str | None = None
    finished_at: str | None = None
    thermal: dict[str, Any] | None = None
    sfem: dict[str, Any] | None = None


class SegmentOut(_Out):
    index: int
    orientation: int | None = None
    n_samples: int | None = None
    t_start_s: float | None = None
    t_end_s: float | None = None
    acc_mean_g: list[float] | None = None
    acc_std_g: list[float] | None = None
    temp_mean_c: float | None = None
    temp_std_c: float | None = None
    position: int | None = None
    step_index: int | None = None


REVISION_HELP = ("1 for a run's first final verdict; N + 1 for a later verdict of the same run that supersedes "
                 "revision N (a resumed batch judged again, a re-judge). Keep the latest revision per run_id")
SUPERSEDES_HELP = "idempotency_key of the record this one replaces; null for revision 1"


class ResultOut(DecisionFields):
    """One MES record: a run's final verdict with its results (design 8)."""

    id: int = Field(description="the record's cursor (result_seq), increasing in commit order")
    idempotency_key: str
    revision: int | None = Field(default=None, description=REVISION_HELP)
    supersedes: str | None = Field(default=None, description=SUPERSEDES_HELP)
    serial: str
    run_id: int | None = None
    batch_id: int | None = None
    station: str | None = Field(default=None, description="the station that measured it (config `name`)")
    slot: str | None = None
    created_at: str | None = None
    thermal: dict[str, Any] | None = None
    sfem: dict[str, Any] | None = None
    program_verify: dict[str, Any] | None = None


class ResultsPage(BaseModel):
    results: list[ResultOut]
    next: str = Field(description="cursor to go on with (pass as since=), never null: the last id of this page, or, "
                      "when the page is empty, the since that was given ('0' when none). Poll with it: each "
                      "record is read once")


class MesResultPayload(DecisionFields):
    """The body of each MES webhook POST (one per verdict record: a run's final verdict, and each
    later one that supersedes it; the same Idempotency-Key header on every retry)."""

    idempotency_key: str
    station: str
    result_id: int | None = Field(default=None, description="the results feed cursor of this record")
    revision: int | None = Field(default=None, description=REVISION_HELP)
    supersedes: str | None = Field(default=None, description=SUPERSEDES_HELP)
    serial: str
    run_id: int | None = None
    batch_id: int | None = None
    slot: str | None = None
    created_at: str | None = None
    thermal: dict[str, AxisThermalOut] | None = Field(default=None, description="per axis: TDB mg/C, TDSF ppm/C")
    streaming: dict[str, Any] | None = None
    offline: dict[str, Any] | None = None
    sfem: dict[str, Any] | None = None


class Health(BaseModel):
    status: str
    version: str
    time: float
    db: str | None = None


class SlotOut(_Out):
    slot: str
    serial: str | None = None
    state: str | None = None
    kind: str | None = Field(default=None, description="serial or can")
    batch_id: int | None = None


class ProfileOut(_Out):
    name: str
    description: str | None = None
    analysis: str | None = Field(default=None, description="what runs at the end: thermal (TDB/TDSF), sfem, or "
                                 "none (logs data only: no calibration result)")
    n_steps: int | None = Field(default=None, description="number of steps")
    builtin: bool | None = Field(default=None, description="built into the station (not from the config)")


class OutboxEntry(_Out):
    id: int | None = None
    idempotency_key: str
    state: str | None = None
    attempts: int = 0
    last_error: str | None = None


class AuditEntry(_Out):
    id: int
    at: str = Field(description="when (UTC, ISO 8601)")
    station: str = Field(description="the station that handled the request (config `name`)")
    actor: str = Field(description="the token's name (never the token)")
    action: str = Field(description="batch.start | batch.abort | prompt.answer | batch.resume | limits.change")
    target: str = Field(description="what it acted on, e.g. 'batch 12'")
    detail: dict[str, Any] = Field(default_factory=dict, description="what the request carried")


class ReplaySummary(_Out):
    duts: int = 0
    unchanged: int = 0
    changed: int = 0
    verdicts_changed: list[dict[str, Any]] = Field(default=[], description="serial, before, after")
    largest_change: dict[str, Any] | None = Field(default=None, description="serial, key, before, after, delta")


class ReplayEntry(_Out):
    """A replay batch (station replay): recorded data re-run through the station, never sent to the MES."""

    batch_id: int
    station: str = ""
    profile: str = ""
    state: str = ""
    replay_of: str = Field(description="the source: 'batch 12 of line-A (...)' or '3 CSV logs'")
    created_at: str | None = None
    ended_at: str | None = None
    summary: ReplaySummary | None = Field(default=None, description="null while the replay runs")
    plate_agrees: bool | None = Field(default=None, description="lamp and fixture agreed with the recording")


class ReplayOut(_Out):
    batch_id: int
    replay_of: str
    state: str = ""
    created_at: str | None = None
    diff: dict[str, Any] | None = Field(default=None, description="station/replay/compare.py ReplayDiff.to_json(): "
                                        "source, before, rtol, atol, summary, agreement, per-DUT changes")


class SpcOut(_Out):
    """station/records/spc.py SpcReport plus the parameters available and the yield tables."""

    parameter: str
    unit: str = ""
    parameters: list[str] = Field(default_factory=list, description="every judged measurement with values")
    points: list[dict[str, Any]] = Field(default_factory=list, description="run_id, batch_id, station, slot, serial, "
                                         "at, value, low, high, verdict; oldest first")
    chart: dict[str, Any] = Field(description="individuals chart: mean, mr_bar, sigma_within, ucl, lcl, mr_ucl, "
                                  "moving_ranges, out_of_control (point indices)")
    capability: dict[str, Any] = Field(description="n, low, high, mean, sigma_within, sigma_overall, cpk, ppk, "
                                       "out_of_spec")
    histogram: dict[str, Any]
    slots: list[dict[str, Any]] = Field(default_factory=list, description="per slot: n, mean, values")
    yield_: dict[str, list[dict[str, Any]]] = Field(default_factory=dict, alias="yield",
                                                     description="per batch, day (UTC), product and station: judged, "
                                                     "passed, marginal, failed, errors, yield_pct")


class ErrorOut(BaseModel):
    detail: str = Field(description="what went wrong, one line for a person")


class ValidationIssue(BaseModel):
    loc: list[str] = Field(description="where: 'body', 'query', 'path' then the field")
    msg: str
    type: str


class ValidationErrorOut(BaseModel):
    """A 422 as it is sent: one line for a person, and (for input that failed the schema) the
    individual problems. Replaces FastAPI's default `HTTPValidationError` in the document."""

    detail: str = Field(description="what is wrong with the input, one line for a person")
    errors: list[ValidationIssue] | None = Field(default=None, description="each problem, when the schema check found them")


_WHAT = {401: "missing, malformed or invalid token", 403: "the token's role may not do this",
         404: "unknown id", 409: "not possible in the current state", 413: "request body too large",
         422: "invalid input", 429: "too many requests of this kind at once: retry after Retry-After seconds",
         503: "no database"}
RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}}


def error_responses(*codes: int, what: dict[int, str] | None = None) -> dict:
    """OpenAPI `responses=` for a router: the error answers its routes give, all {"detail": "..."}."""
    what = {**_WHAT, **(what or {})}
    out = {}
    for c in codes:
        out[c] = {"model": ValidationErrorOut if c == 422 else ErrorOut, "description": what.get(c, "error")}
        if c in (429, 503):
            out[c]["headers"] = RETRY_AFTER
    return out


def install_openapi(app) -> None:
    """Make /openapi.json describe what is sent (a schemathesis run checks every answer against it):

    - every 422 is a `ValidationErrorOut` (FastAPI documents its own list-shaped default, which the
      app's handler replaces with {"detail": "...", "errors": [...]});
    - an operation with a request body can also answer 413 (web/guard.py) and 401 (the token is
      checked before the body is read)."""
    from fastapi.openapi.utils import get_openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes,
                          webhooks=app.webhooks.routes, tags=app.openapi_tags)
        comps = doc.setdefault("components", {}).setdefault("schemas", {})
        ref = "#/components/schemas/ValidationErrorOut"
        for name, sch in ValidationErrorOut.model_json_schema(ref_template="#/components/schemas/{model}").get("$defs", {}).items():
            comps.setdefault(name, sch)
        main = ValidationErrorOut.model_json_schema(ref_template="#/components/schemas/{model}")
        main.pop("$defs", None)
        comps["ValidationErrorOut"] = main
        err_ref = {"$ref": "#/components/schemas/ErrorOut"}
        comps.setdefault("ErrorOut", ErrorOut.model_json_schema())
        for item in doc.get("paths", {}).values():
            for op in item.values():
                if not isinstance(op, dict) or "responses" not in op:
                    continue
                resp = op["responses"]
                if "422" in resp:
                    resp["422"]["content"] = {"application/json": {"schema": {"$ref": ref}}}
                if "requestBody" in op:
                    resp.setdefault("401", {"description": _WHAT[401], "content": {"application/json": {"schema": err_ref}}})
                    resp.setdefault("413", {"description": _WHAT[413], "content": {"application/json": {"schema": err_ref}}})
        for item in (doc.get("webhooks") or {}).values():
            for op in item.values():
                # FastAPI gives the webhook its own 422 (HTTPValidationError): that would be the MES's
                # answer, which the station does not read (2xx: stored; anything else: retried)
                if isinstance(op, dict):
                    (op.get("responses") or {}).pop("422", None)
        text = __import__("json").dumps(doc)
        for name in ("HTTPValidationError", "ValidationError"):
            if f'"#/components/schemas/{name}"' not in text:
                comps.pop(name, None)
        app.openapi_schema = doc
        return doc

    app.openapi = openapi
