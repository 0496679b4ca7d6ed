"""Pydantic models of the REST API (design 5.3): they validate input (422 with a message) and make
the OpenAPI document (/openapi.json, rendered at /docs) describe every route and every field it sends.

Response models allow extra fields at runtime (`extra="allow"`, web/schemas_common.py `_Out`): the
daemon or the database may add a field and no client breaks, and no route answers 500 because of
it. That is forward compatibility, not licence: every field a route sends must be declared here,
typed and described (units in the description), so that a client generated from /openapi.json sees
all of it. tests/test_openapi_truth.py enforces this: it validates the live answers of every GET
route against the document with undeclared fields forbidden, and fails on an object schema that
says nothing of its keys unless it is a documented free-form map (FREE_FORM). The big objects the
daemon computes for each slot of the polled batch status (its calibration result, its verification)
are documented by models but passed through unvalidated at runtime (schemas_common.passed_through:
cheaper on the daemon's event loop); the same test holds them to their models.

The response models live by subject: web/schemas_common.py (shared parts), schemas_live.py (the
daemon's batches and slots), schemas_program.py (program and verify, live and stored),
schemas_thermal.py (a DUT's calibration result), schemas_history.py
(DUTs, runs, the MES feed), schemas_diagnosis.py, schemas_records.py (audit, SPC, replays); this
module holds the request models, the small answers, the error models and the document's fix-ups,
and re-exports the rest so routes import from one place.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from web.schemas_records import AuditEntry, ReplayEntry, ReplayOut, ReplaySummary, SpcOut  # noqa: F401  (moved there)
from web.schemas_common import (  # noqa: F401  (re-exported)
    DOCUMENTED_ONLY, FREE_FORM, AxisThermalOut, DecisionFields, DecisionOut, ProgramVerifyOut, ThermalAxes,
    VerdictName, _Out,
)
from web.schemas_diagnosis import DiagnosisOut, DiagnosticModelOut  # noqa: F401
from web.schemas_history import (  # noqa: F401
    DutOut, DutSummary, MesResultPayload, OutboxEntry, ResultOut, ResultsPage, RunOut, SegmentOut, YieldOut,
)
from web.schemas_live import (  # noqa: F401
    BatchStatus, DecisionSummary, Health, Prompt, SlotOut, SlotStatus, SortingEntry, StepInfo, StepRow, TimeLeft,
)

SLOT_PATTERN = r"^[A-Za-z0-9_.:\-/]{1,64}$"


class Me(_Out):
    """Who the token belongs to (web/auth.py Principal)."""

    name: str = Field(description="the token's name from the config (never the token)")
    role: Literal["operator", "mes", "admin"] = Field(description="what the token may do: operator starts and "
                                                      "aborts batches and answers prompts, mes reads results, admin all")


class ProfileOut(_Out):
    """A profile the station can run (station/daemon/supervisor.py profiles_info)."""

    name: str = Field(description="profile name (POST /api/batches `profile`)")
    description: str | None = Field(default=None, description="what it does, for the operator")
    analysis: str | None = Field(default=None, description="what runs at the end: thermal (TDB/TDSF), sfem, or "
                                 "none (logs data only: no calibration result)")
    n_steps: int | None = Field(default=None, description="number of steps")
    builtin: bool | None = Field(default=None, description="built into the station (not from the config)")
    program_verify: bool | None = Field(default=None, description="it ends with program and verify (the "
                                        "coefficients are written into the board and checked)")


class BatchCreated(_Out):
    id: int = Field(description="the new batch's id")


class BatchCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    profile: str = Field(min_length=1, max_length=64, description="profile name, see GET /api/profiles")
    slots: list[Annotated[str, Field(min_length=1, max_length=64, pattern=r"\S")]] | None = Field(
        default=None, description="slots to test; null = every connected slot", min_length=1, max_length=1024
    )
    operator: str = Field(min_length=1, max_length=100, description="operator name or badge id (required: the "
                          "person who runs the batch, recorded on every run and in the audit trail)")
    work_order: str = Field(default="", max_length=64, description="work order (typed or scanned)")
    part_number: str = Field(default="", max_length=64, description="part number of the boards")
    part_revision: str = Field(default="", max_length=32, description="revision of that part")
    lot: str = Field(default="", max_length=64, description="lot of the boards")
    labels: dict[Annotated[str, Field(min_length=1, max_length=64)], Annotated[str, Field(max_length=64)]] | None = Field(
        default=None, description="slot -> serial on the part's label (scanned or typed; optional per slot): a slot "
        "whose board reports another serial is stopped with the reason")

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

    @field_validator("work_order", "part_number", "part_revision", "lot")
    @classmethod
    def _trimmed(cls, v: str) -> str:
        return v.strip()

    @model_validator(mode="after")
    def _labels_of_chosen_slots(self) -> "BatchCreate":
        if self.labels and self.slots is not None:
            extra = sorted(set(self.labels) - set(self.slots))
            if extra:
                raise ValueError(f"labels given for slot(s) not in the batch: {', '.join(extra)}")
        return self


class RetestCreate(BaseModel):
    """Retest the slots that ended error, fail or marginal in an ended batch: the same profile, work
    order, part number, revision and lot; the operator who starts it; the parts' labels scanned
    again."""
    model_config = ConfigDict(extra="forbid")

    operator: str = Field(min_length=1, max_length=100, description="operator name or badge id (required)")
    labels: dict[Annotated[str, Field(min_length=1, max_length=64)], Annotated[str, Field(max_length=64)]] | None = Field(
        default=None, description="slot -> serial on the part's label, scanned again for the retest (optional per "
        "slot: a slot without one runs unchecked). null: the labels scanned for the batch, except a label its "
        "board contradicted (a label mismatch), which is refused (409): scan that part's label again")
    slots: list[Annotated[str, Field(min_length=1, max_length=64, pattern=r"\S")]] | None = Field(
        default=None, min_length=1, max_length=1024, description="null: every slot that ended error, fail or "
        "marginal; a list: some of those (another slot is a 409)")

    @field_validator("operator")
    @classmethod
    def _not_blank(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("must not be blank")
        return v.strip()

    @field_validator("slots")
    @classmethod
    def _no_repeat(cls, v: list[str] | None) -> list[str] | None:
        if v is not None and len(set(v)) != len(v):
            raise ValueError("slots must not repeat a slot")
        return v


class PromptAnswer(BaseModel):
    model_config = ConfigDict(extra="forbid")

    prompt_id: int = Field(ge=0, description="the id of the prompt being answered (GET .../prompt)")
    answer: Literal["done", "abort", "cannot"] = Field(
        default="done", description="done: the operator did what the prompt asks; cannot: the operator cannot do it "
        "(the DUTs it concerns end as error with the note); abort: abort the batch")
    note: str = Field(default="", max_length=500, description="the operator's words (required for 'cannot')")

    @model_validator(mode="after")
    def _note_for_cannot(self) -> "PromptAnswer":
        self.note = self.note.strip()
        if self.answer == "cannot" and not self.note:
            raise ValueError("say why it cannot be done (note): it is recorded with the DUTs it ends")
        return self


class Ack(_Out):
    ok: bool = Field(default=True, description="the request was carried out")
    detail: str = Field(default="", description="what was done, in words")


class ErrorOut(BaseModel):
    detail: str = Field(description="what went wrong, one line for a person")


class ValidationIssue(BaseModel):
    loc: list[str] = Field(description="where: 'body', 'query', 'path' then the field")
    msg: str = Field(description="what is wrong, in words")
    type: str = Field(description="pydantic's error type, e.g. missing, string_too_long")


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


HEALTH_OPERATION = "health_api_health_get"  # never 503: it reports the database, never waits on it
DB_DOWN = ("the station's database is not available (not answering, unreachable, its file deleted: "
           "web/db_gate.py); the detail says since when. Retry later")


def install_openapi(app) -> None:
    """Make /openapi.json describe what is sent (a schemathesis run checks every answer against it):

    - every 422 is a `ValidationErrorOut` (FastAPI documents its own list-shaped default, which the
      app's handler replaces with {"detail": "...", "errors": [...]});
    - an operation with a request body can also answer 413 (web/guard.py) and 401 (the token is
      checked before the body is read);
    - the models of fields passed through at runtime (DOCUMENTED_ONLY) are components too."""
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
        for model in DOCUMENTED_ONLY:  # fields passed through at runtime, documented as these models
            sch = model.model_json_schema(ref_template="#/components/schemas/{model}", mode="serialization")
            for name, sub in sch.pop("$defs", {}).items():
                comps.setdefault(name, sub)
            comps.setdefault(model.__name__, sch)
        err_ref = {"$ref": "#/components/schemas/ErrorOut"}
        comps.setdefault("ErrorOut", ErrorOut.model_json_schema())
        for item in doc.get("paths", {}).values():
            for op in item.values():
                if not isinstance(op, dict) or "responses" not in op:
                    continue
                resp = op["responses"]
                if "422" in resp:
                    resp["422"]["content"] = {"application/json": {"schema": {"$ref": ref}}}
                if op.get("operationId") != HEALTH_OPERATION:  # every route may meet a database that is down
                    resp.setdefault("503", {"description": DB_DOWN, "headers": RETRY_AFTER,
                                            "content": {"application/json": {"schema": err_ref}}})
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
