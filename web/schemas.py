"""Pydantic models of the REST API (design 5.3): they validate input (422 with a message) and make
the OpenAPI document (/openapi.json, rendered at /docs) describe every route.

Response models allow extra fields so that the daemon and the database may add information without
breaking the contract; the fields named here are the ones clients may rely on.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

SLOT_PATTERN = r"^[A-Za-z0-9_.:\-/]{1,64}$"


class _Out(BaseModel):
    model_config = ConfigDict(extra="allow")


class BatchCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    profile: str = Field(min_length=1, max_length=64, description="profile name, see GET /api/profiles")
    slots: list[str] | None = Field(
        default=None, description="slots to test; null = every connected slot", max_length=1024
    )
    operator: str = Field(min_length=1, max_length=100, description="operator name or badge id")

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


class SlotStatus(_Out):
    slot: str
    serial: str | None = None
    state: str | None = None
    segments: int = Field(default=0, description="segments logged in this batch")
    error: str | None = Field(default=None, description="fault reason, when faulted")
    temp_c: float | None = None
    samples: int | None = None


class BatchStatus(_Out):
    id: int
    profile: str | None = None
    operator: str | None = None
    state: str
    step: StepInfo | None = None
    slots: list[SlotStatus] = []
    error: str | None = None
    prompt: dict[str, Any] | None = None


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


class DutOut(_Out):
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


class DutSummary(_Out):
    serial: str
    sensor: str | None = None
    runs: int = 0
    last_run_id: int | None = None
    last_state: str | None = None
    last_at: str | None = None


class RunOut(_Out):
    id: int
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


class ResultOut(_Out):
    id: int
    idempotency_key: str
    serial: str
    run_id: int | None = None
    batch_id: int | None = None
    slot: str | None = None
    created_at: str | None = None
    thermal: dict[str, Any] | None = None
    sfem: dict[str, Any] | None = None


class ResultsPage(BaseModel):
    results: list[ResultOut]
    next: str | None = Field(description="cursor for the next page (pass as since=); null when this page is the last")


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


class OutboxEntry(_Out):
    id: int | None = None
    idempotency_key: str
    state: str | None = None
    attempts: int = 0
    last_error: str | None = None


class ErrorOut(BaseModel):
    detail: str = Field(description="what went wrong, one line for a person")


def error_responses(*codes: int) -> dict:
    """OpenAPI `responses=` for a router: the error answers its routes give, all {"detail": "..."}."""
    what = {401: "missing, malformed or invalid token", 403: "the token's role may not do this",
            404: "unknown id", 409: "not possible in the batch's current state", 422: "invalid input",
            503: "no database"}
    return {c: {"model": ErrorOut, "description": what.get(c, "error")} for c in codes}
