"""Building blocks the REST response models share (web/schemas.py explains the policy): per-axis
values, thermal coefficients as stored and as computed, program and verify, the station's decision.

Each class mirrors what one producer sends (named in its docstring), so that a change there shows
up in tests/test_openapi_truth.py as an undeclared or mistyped field.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, WithJsonSchema, model_validator

from station.decisions.measurements import declared
from station.decisions.verdicts import VERDICTS
from station.records.causes import reason_code as _code_of_reason

FREE_FORM = "x-free-form"  # marks a documented free-form map in the document (its keys are data)


class _Out(BaseModel):
    """Response model base: extra fields pass (forward compatible at runtime); the test forbids them."""

    model_config = ConfigDict(extra="allow")


def free_form(description: str, **kw: Any) -> Any:
    """A field whose value is a free-form JSON object by design (see FREE_FORM), with why in words."""
    return Field(description=description, json_schema_extra={FREE_FORM: True}, **kw)


# Models documented in /openapi.json although no route validates with them (see passed_through);
# web/schemas.py install_openapi adds them to the document's components.
DOCUMENTED_ONLY: list[type[BaseModel]] = []


def passed_through(*models: type[BaseModel], nullable: bool = True) -> Any:
    """The type of a field documented as `models` (anyOf) but passed through unvalidated at runtime:
    for the big objects the daemon computes (a slot's calibration result, its verification) that
    ride on the polled batch status: validating them model by model made a 64-slot status about 7x
    slower to render on the daemon's event loop, and changes nothing (they are the producer's
    JSON). That they match their models is what tests/test_openapi_truth.py checks, on the wire."""
    DOCUMENTED_ONLY.extend(m for m in models if m not in DOCUMENTED_ONLY)
    refs: list[dict[str, Any]] = [{"$ref": f"#/components/schemas/{m.__name__}"} for m in models]
    if nullable:
        refs.append({"type": "null"})
    schema = refs[0] if len(refs) == 1 else {"anyOf": refs}
    return Annotated[dict[str, Any] | None if nullable else dict[str, Any], WithJsonSchema(schema)]


def one_of(values: tuple[str, ...], description: str, *, nullable: bool = True, **kw: Any) -> Any:
    """A string field whose values the document enumerates, while the runtime accepts any string:
    a new value from the daemon must not turn its status into a 500; tests/test_openapi_truth.py
    (which validates against the document) reports it instead."""
    enum: list[Any] = [*values, None] if nullable else list(values)
    return Field(description=description, json_schema_extra={"enum": enum}, **kw)


VerdictName = Literal["pass", "marginal", "fail", "error"]  # station/decisions/verdicts.py VERDICTS (tested)


class PerAxis(_Out):
    """One number per axis (the unit is in the field that holds it); null where not known."""

    x: float | None = Field(default=None, description="x axis")
    y: float | None = Field(default=None, description="y axis")
    z: float | None = Field(default=None, description="z axis")


class PerAxisBool(_Out):
    """One yes/no per axis."""

    x: bool | None = Field(default=None, description="x axis")
    y: bool | None = Field(default=None, description="y axis")
    z: bool | None = Field(default=None, description="z axis")


class AxisThermalOut(_Out):
    """TDB and TDSF of one axis (contracts/types.py AxisThermal, db/repository.py thermal_json)."""

    tdb_mg_per_c: float | None = Field(default=None, description="thermal drift of bias, mg/C")
    tdsf_ppm_per_c: float | None = Field(default=None, description="thermal drift of scale factor, ppm/C")
    tdb_sigma_mg_per_c: float | None = Field(default=None, description="1-sigma of TDB, mg/C (null: not known)")
    tdsf_sigma_ppm_per_c: float | None = Field(default=None, description="1-sigma of TDSF, ppm/C (null: not known)")
    tdsf_clamped: bool | None = Field(default=None, description="a positive TDSF was clamped to 0 (physics: TDSF <= 0)")


class ThermalAxes(_Out):
    """TDB/TDSF per axis."""

    x: AxisThermalOut | None = Field(default=None, description="x axis")
    y: AxisThermalOut | None = Field(default=None, description="y axis")
    z: AxisThermalOut | None = Field(default=None, description="z axis")


class ThermalRow(ThermalAxes):
    """One stored thermal result of one method (db/repository.py thermal_json)."""

    id: int = Field(description="the stored result's id")
    method: str = Field(description="streaming (the live calibrator) or offline (the fit over all samples)")
    n_segments: int | None = Field(default=None, description="segments the result is computed from")
    created_at: str | None = Field(default=None, description="when it was stored (ISO 8601 UTC)")


class ThermalByMethod(_Out):
    """The latest stored thermal result per method."""

    streaming: ThermalRow | None = Field(default=None, description="the live streaming calibrator's result")
    offline: ThermalRow | None = Field(default=None, description="the offline fit over the run's samples")


class WrittenCoefficients(_Out):
    """The coefficients written into the board (program and verify)."""

    tdb_mg_per_c: PerAxis | None = Field(default=None, description="TDB written per axis, mg/C")
    tdsf_ppm_per_c: PerAxis | None = Field(default=None, description="TDSF written per axis, ppm/C")


class ProgramVerifyOut(_Out):
    """Program and verify of one stored run (db/repository.py program_verify_json, design 4)."""

    programmed: bool | None = Field(default=None, description="coefficients written and read back identical")
    written: WrittenCoefficients | None = Field(default=None, description="what was written; null when nothing was")
    crc: str | None = Field(default=None, description="CRC-32 of the written values (8 hex digits)")
    readback_crc: str | None = Field(default=None, description="CRC-32 the board reported back (8 hex digits)")
    readback_identical: bool | None = Field(default=None, description="programmed and crc == readback_crc")
    comp_on: bool | None = Field(default=None, description="the board's own compensation is switched on")
    attempts: int | None = Field(default=None, description="write attempts used (0: none)")
    error_kind: str | None = Field(default=None, description="why programming failed (e.g. refused, crc_mismatch, "
                                   "link, no_result); null when it did not fail")
    error: str | None = Field(default=None, description="the failure in words; null when it did not fail")
    verified: bool | None = Field(default=None, description="the verification heat passed; null: not verified (yet)")
    e_before_mg: PerAxis | None = Field(default=None, description="verified drift error E before compensation "
                                        "(first pass, uncompensated) per axis, mg over the 70 C range")
    e_after_mg: PerAxis | None = Field(default=None, description="verified drift error E with the board's "
                                       "compensation on, per axis, mg")
    flags: list[str] = Field(default_factory=list, description="named problems of the verification (residual drift, "
                             "curvature, ...)")
    updated_at: str | None = Field(default=None, description="when the record last changed (ISO 8601 UTC)")


class CheckOut(_Out):
    """One measurement against one limit (station/decisions/verdicts.py Check; its fields: CHECK_FIELDS)."""

    measurement: str = Field(description="what was judged: one of the station's measurements (station/decisions/"
                             "measurements.py: " + ", ".join(d.name for d in declared()) + ") or a site limit's own")
    axis: str | None = Field(default=None, description="x, y, z, or null for a whole-DUT measurement")
    value: float | None = Field(default=None, description="the measured value, in `unit`")
    sigma: float | None = Field(default=None, description="its combined 1-sigma uncertainty, in `unit`")
    unit: str = Field(default="", description="unit of value, sigma, low and high (e.g. mg/C, ppm/C, %FS)")
    low: float | None = Field(default=None, description="lower limit, in `unit` (null: none)")
    high: float | None = Field(default=None, description="upper limit, in `unit` (null: none)")
    outcome: str = one_of(VERDICTS, "this check's outcome", nullable=False)
    reason: str = Field(default="", description="plain words when it did not pass")


class DecisionOut(_Out):
    """The station's decision on one run as the daemon and the MES record carry it
    (station/decisions/verdicts.py Verdict.to_json: VERDICT_FIELDS; + attempt and run_id,
    station/decisions/moment.py)."""

    verdict: str | None = one_of(VERDICTS, "the verdict", default=None)
    grade: str | None = Field(default=None, description="bin from the product's config; hold, reject, retest")
    tray: str | None = Field(default=None, description="where the operator puts the board")
    reason: str | None = Field(default=None, description="one line: the worst reasons (at most 3) or 'all limits met'")
    reasons: list[str] | None = Field(default=None, description="every reason, worst first")
    failures: list[CheckOut] | None = Field(default=None, description="the checks that did not pass")
    checks: list[CheckOut] | None = Field(default=None, description="every check (not in the live batch status: "
                                          "the full list is stored with the run)")
    product: str | None = Field(default=None, description="the product (limits set) the DUT was judged as")
    limits_name: str | None = Field(default=None, description="limits set the DUT was judged by")
    limits_version: str | None = Field(default=None, description="version of that limits set")
    attempt: int | None = Field(default=None, description="the serial's attempt number (retest: 2, 3, ...; 0: no "
                                "attempt, the run was stopped for a label mismatch before it tested the part)")
    run_id: int | None = Field(default=None, description="the run judged")


class CodedWords(BaseModel):
    """A response carrying the daemon's English words (a reason, a fault) and, beside each, the code the
    page translates them by (web/static/i18n). The codes are derived here from the words
    (station/records/causes.py reason_code), never by each producer: every response that carries the
    words carries their code, and the record keeps the words as the station wrote them.
    `words_codes`: code field -> the words field it names (a subclass extends its base's)."""

    words_codes: ClassVar[dict[str, str]] = {}

    @model_validator(mode="after")
    def _codes_from_words(self) -> Self:
        for code, words in self.words_codes.items():
            setattr(self, code, _code_of_reason(getattr(self, words)))
        return self


class DecisionFields(_Out, CodedWords):
    """The station's decision on a DUT run (station/decisions/verdicts.py DECISION_FIELDS); null while it is not
    judged."""

    verdict: VerdictName | None = Field(
        default=None, description="pass | marginal (an uncertainty interval crosses a limit, or a value is in a "
        "marginal band) | fail | error (faulted, incomplete or not measured: never pass)")
    grade: str | None = Field(default=None, description="bin from the product's config: e.g. A, B; "
                              "'hold' for marginal, 'reject' for fail, 'retest' for error")
    tray: str | None = Field(default=None, description="where the operator puts the board")
    reason: str | None = Field(default=None, description="plain words, e.g. 'z TDSF -612 ppm/C, limit -500'")
    attempt: int | None = Field(default=None, description="the serial's attempt number (retest: 2, 3, ...; 0: no "
                                "attempt, the run was stopped for a label mismatch before it tested the part)")
    limits_name: str | None = Field(default=None, description="limits set the DUT was judged by")
    limits_version: str | None = Field(default=None, description="version of that limits set")

    reason_code: str | None = Field(default=None, description="the machine code of `reason` "
                                    "(station/records/causes.py reason_code, e.g. 'label_mismatch', 'limit_exceeded'): "
                                    "the page says the cause in the operator's language from it (web/static/i18n); "
                                    "null when no rule names the words (shown as they are)")

    words_codes: ClassVar[dict[str, str]] = {"reason_code": "reason"}


class StoredDecision(DecisionFields):
    """A stored decision: DecisionFields plus when it was made (db/repository.py _decision_json)."""

    judged_at: str | None = Field(default=None, description="when the verdict was stored (ISO 8601 UTC); null "
                                  "while not judged")


class TraceFields(_Out):
    """What the batch was started for (contracts/trace.py); '' when not given."""

    work_order: str = Field(default="", description="work order ('' when not given)")
    part_number: str = Field(default="", description="part number ('' when not given)")
    part_revision: str = Field(default="", description="part revision ('' when not given)")
    lot: str = Field(default="", description="lot ('' when not given)")


SFEM_HELP = ("SFEM result (sensors2023) as stored: the record contracts/sfem_result.py SfemResult (the JSON of "
             "`station sfem --json`: the reference step's fit, steps, thermal, model_check; runs stored before it: one "
             "fit or {steps: [fit, ...], polynomial_coefficients}); null when the run has none")
