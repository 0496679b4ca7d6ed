"""The CFX messages of a batch (IPC-2591, the CFX SDK's message classes; docs/cfx.md), built from
what the station stored and decided: a batch row with its runs, a verdict record, a run's segment
temperatures. Pure: records in, typed envelopes out, no I/O, no clock, so a message rebuilt from the
same records is the same message (same UniqueID) and a test can check it without a broker.

Why these choices (docs/cfx.md has the table of every field and where it comes from):
- one work transaction per batch: the plate is the carrier, its slots the unit positions; the
  TransactionID is a name-based UUID of (station, batch), so every message of a batch names it
  without storing it;
- one UnitsTested per verdict record (a run's final verdict, and each later one that supersedes
  it), sent only once the verdict is stored;
- every UniqueID is a name-based UUID of the message's outbox key: a resend after a lost
  acknowledgement carries the same UniqueID, which is how the line recognises it.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Literal, TypedDict, Union

from contracts.json_safe import finite_or_none
from db.queries_cfx import BatchFacts, RunFacts, TempStats, cfx_prefix

CFX_VERSION = "2.1"  # the IPC-2591 revision the message shapes follow (CFX SDK CFXEnvelope.CFXVERSION)
# The namespace of the station's name-based UUIDs (UniqueID, TransactionID, test and measurement ids).
CFX_NAMESPACE = uuid.UUID("6f1c63a4-2d0e-5b7a-9a43-3c2f6c1e8b10")

WORK_STARTED = "CFX.Production.WorkStarted"
WORK_COMPLETED = "CFX.Production.WorkCompleted"
UNITS_TESTED = "CFX.Production.TestAndInspection.UnitsTested"
STATION_STATE_CHANGED = "CFX.ResourcePerformance.StationStateChanged"
CALIBRATION_PERFORMED = "CFX.ResourcePerformance.CalibrationPerformed"

# ResourceState (SEMI E58 codes, serialized as numbers): idle, working, down
SBY_NO_PRODUCT = 2200
PRD_REGULAR_WORK = 1100
USD = 5000

TestResult = Literal["Passed", "Failed", "Error", "Aborted", "Skipped"]
UnitStatus = Literal["Pass", "Fail", "Scrap", "Skip"]
WorkResult = Literal["Completed", "Failed", "Aborted", "Skipped"]


class WorkOrderIdentifier(TypedDict):
    WorkOrderId: str
    Batch: str | None


class UnitPosition(TypedDict):
    UnitIdentifier: str
    PositionNumber: int
    PositionName: str
    X: float
    Y: float
    Z: float | None
    Rotation: float
    FlipX: bool
    FlipY: bool
    Status: UnitStatus


class WorkStarted(TypedDict):
    PrimaryIdentifier: str
    HermesIdentifier: None
    TransactionID: str
    Lane: None
    UnitCount: int
    Units: list[UnitPosition]
    RecipeName: str
    Revision: None
    WorkOrderIdentifier: WorkOrderIdentifier | None


class WorkCompleted(TypedDict):
    TransactionID: str
    Result: WorkResult
    PrimaryIdentifier: str
    HermesIdentifier: None
    UnitCount: int
    Units: list[UnitPosition]


class Operator(TypedDict):
    OperatorIdentifier: str
    ActorType: Literal["Human"]
    LastName: None
    FirstName: None
    LoginName: str


class SamplingInformation(TypedDict):
    SamplingMethod: Literal["NoSampling"]
    LotSize: None
    SampleSize: None


# "$type" names the polymorphic CFX structure (Newtonsoft TypeNameHandling.Auto, as the SDK writes it)
TemperatureCondition = TypedDict("TemperatureCondition", {
    "$type": str, "StartTime": str | None, "EndTime": str | None,
    "MeanValue": float, "MedianValue": float, "MaxValue": float, "MinValue": float,
})


class NumericValue(TypedDict):
    Value: float
    ValueUnits: str
    ExpectedValue: None
    ExpectedValueUnits: None
    MinimumAcceptableValue: None
    MinimumAcceptableValueUnits: None
    MaximumAcceptableValue: None
    MaximumAcceptableValueUnits: None


NumericMeasurement = TypedDict("NumericMeasurement", {
    "$type": str, "UniqueIdentifier": str, "MeasurementName": str, "TimeRecorded": str | None,
    "Sequence": int, "Result": TestResult, "CRDs": None, "MeasuredValue": NumericValue,
})


class Test(TypedDict):
    UniqueIdentifier: str
    TestName: str
    TestStartTime: str | None
    TestEndTime: str | None
    TestConditions: list[TemperatureCondition]
    TestProcedure: str
    Comments: str
    Result: TestResult
    Error: str | None
    SymptomsFound: list[None]
    DefectsFound: list[None]
    Measurements: list[NumericMeasurement]


class TestedUnit(TypedDict):
    UnitIdentifier: str
    UnitPositionNumber: int | None
    OverallResult: TestResult
    Tests: list[Test]


class UnitsTested(TypedDict):
    TransactionId: str  # sic: this message spells it "Id" (UnitsTested.cs)
    TestMethod: Literal["Automated"]
    Tester: Operator | None
    RecipeName: str
    RecipeRevision: str | None
    SamplingInformation: SamplingInformation
    TestedUnits: list[TestedUnit]


class Fault(TypedDict):
    TransactionID: str
    Cause: Literal["ProcessError"]
    Severity: Literal["Error"]
    FaultCode: str
    FaultOccurrenceId: str
    Lane: None
    Stage: None
    SideLocation: Literal["Unknown"]
    AccessType: Literal["Unknown"]
    Description: str
    OccurredAt: str | None


class StationStateChanged(TypedDict):
    OldState: int
    OldStateDuration: str | None
    NewState: int
    RelatedFault: Fault | None


class Calibration(TypedDict):
    CalibrationCode: str
    CalibrationType: Literal["General"]
    Comments: str
    Status: Literal["Ok", "Unknown"]
    CalibrationTime: None
    Measurements: list[None]


class CalibrationPerformed(TypedDict):
    TransactionID: str
    Calibration: Calibration


MessageBody = Union[WorkStarted, WorkCompleted, UnitsTested, StationStateChanged, CalibrationPerformed]


class Envelope(TypedDict):
    MessageName: str
    Version: str
    TimeStamp: str
    UniqueID: str
    Source: str
    Target: None
    RequestID: None
    MessageBody: MessageBody


@dataclass(frozen=True)
class Outgoing:
    """One message for the outbox: its key (stable, per station), and the envelope."""

    key: str
    envelope: Envelope


@dataclass(frozen=True)
class VerdictFacts:
    """One verdict record (db/queries_mes.py results_since) as UnitsTested needs it."""

    result_seq: int
    run_id: int
    batch_id: int
    slot: str
    serial: str
    verdict: str | None
    grade: str | None
    tray: str | None
    reason: str
    judged_at: datetime | None
    started_at: datetime | None
    ended_at: datetime | None
    attempt: int
    revision: int
    route_check: str | None
    limits_name: str | None
    limits_version: str | None
    # per axis (x, y, z): TDB mg/C and TDSF ppm/C of the run's preferred thermal result, None if absent
    tdb_mg_per_c: tuple[float | None, float | None, float | None] = (None, None, None)
    tdsf_ppm_per_c: tuple[float | None, float | None, float | None] = (None, None, None)


# ------------------------------------------------------------------ helpers


def name_uuid(*parts: object) -> str:
    """A name-based UUID (RFC 4122 v5) of the parts: the same parts give the same id on any restart."""
    return str(uuid.uuid5(CFX_NAMESPACE, "/".join(str(p) for p in parts)))


def transaction_id(station: str, batch_id: int) -> str:
    return name_uuid("transaction", station, batch_id)


def iso(t: datetime) -> str:
    """ISO 8601 with its offset (CFX: a TimeStamp must include the time zone); naive = UTC."""
    return (t if t.tzinfo is not None else t.replace(tzinfo=timezone.utc)).isoformat()


def iso_or_none(t: datetime | None) -> str | None:
    return None if t is None else iso(t)


def timespan(seconds: float) -> str:
    """A duration as .NET's TimeSpan serializes it ([d.]hh:mm:ss[.fffffff]), what the SDK reads."""
    ticks = max(0, round(seconds * 10_000_000))
    whole, frac = divmod(ticks, 10_000_000)
    days, rest = divmod(whole, 86_400)
    h, rest = divmod(rest, 3600)
    m, s = divmod(rest, 60)
    out = f"{days}." if days else ""
    out += f"{h:02d}:{m:02d}:{s:02d}"
    return out + (f".{frac:07d}" if frac else "")


def default_handle(station: str) -> str:
    """The station's CFX handle when the config names none."""
    return f"//thermal-cal-station/{station}"


def message_key(station: str, what: str, n: object) -> str:
    """The outbox key of one message: "cfx/<station>/<what>/<n>" (db/queries_cfx.py cfx_prefix)."""
    return f"{cfx_prefix(station)}{what}/{n}"


def envelope(name: str, body: MessageBody, source: str, at: datetime, key: str) -> Envelope:
    """The CFX envelope (CFXEnvelope.cs): TimeStamp is when the event took place, not when sent."""
    return {"MessageName": name, "Version": CFX_VERSION, "TimeStamp": iso(at), "UniqueID": name_uuid("message", key),
            "Source": source, "Target": None, "RequestID": None, "MessageBody": body}


def position_of(batch: BatchFacts, slot: str) -> int | None:
    """A slot's CFX position number: its 1-based place in the batch's configured slots."""
    return batch.slots.index(slot) + 1 if slot in batch.slots else None


def unit_status(run: RunFacts) -> UnitStatus:
    if run.route_check == "refused":
        return "Skip"  # the MES refused the part: it was never tested here
    return "Pass" if run.verdict == "pass" else "Fail"


def test_result(verdict: str | None, route_check: str | None) -> TestResult:
    """The station's verdict as a CFX TestResult: marginal (the interval crosses a limit, on hold)
    is no pass; a part the MES refused was skipped, never tested."""
    if route_check == "refused":
        return "Skipped"
    if verdict == "pass":
        return "Passed"
    return "Failed" if verdict in ("marginal", "fail") else "Error"


def _unit(batch: BatchFacts, run: RunFacts, status: UnitStatus) -> UnitPosition:
    return {"UnitIdentifier": run.serial, "PositionNumber": position_of(batch, run.slot) or 0, "PositionName": run.slot,
            "X": 0.0, "Y": 0.0, "Z": None, "Rotation": 0.0, "FlipX": False, "FlipY": False, "Status": status}


def _primary(batch: BatchFacts) -> str:
    return f"{batch.station}/batch/{batch.batch_id}"


# ------------------------------------------------------------------ messages


def work_started(batch: BatchFacts, source: str) -> Outgoing:
    """The batch's work transaction starts (at the batch's creation); its units are the runs stored
    by then (WorkCompleted lists them all again, as the spec allows when they were not all known)."""
    key = message_key(batch.station, "work-started", batch.batch_id)
    units = sorted((_unit(batch, r, "Pass") for r in batch.runs), key=lambda u: u["PositionNumber"])
    body: WorkStarted = {
        "PrimaryIdentifier": _primary(batch), "HermesIdentifier": None,
        "TransactionID": transaction_id(batch.station, batch.batch_id), "Lane": None,
        "UnitCount": len(units), "Units": units, "RecipeName": batch.profile, "Revision": None,
        "WorkOrderIdentifier": {"WorkOrderId": batch.work_order, "Batch": batch.lot or None} if batch.work_order else None,
    }
    return Outgoing(key, envelope(WORK_STARTED, body, source, batch.created_at, key))


def work_result(state: str) -> WorkResult:
    """finished -> Completed, failed -> Failed; aborted or interrupted (a resumable stop) -> Aborted."""
    if state == "finished":
        return "Completed"
    return "Failed" if state == "failed" else "Aborted"


def work_completed(batch: BatchFacts, source: str) -> Outgoing:
    """The batch ended (finished, failed, aborted or interrupted): every unit with its status."""
    key = message_key(batch.station, "work-completed", batch.batch_id)
    units = sorted((_unit(batch, r, unit_status(r)) for r in batch.runs), key=lambda u: u["PositionNumber"])
    body: WorkCompleted = {
        "TransactionID": transaction_id(batch.station, batch.batch_id), "Result": work_result(batch.state),
        "PrimaryIdentifier": _primary(batch), "HermesIdentifier": None, "UnitCount": len(units), "Units": units,
    }
    return Outgoing(key, envelope(WORK_COMPLETED, body, source, batch.ended_at or batch.created_at, key))


def station_state_changed(batch: BatchFacts, source: str, starting: bool) -> Outgoing:
    """Idle -> working at the batch's start; working -> idle (finished, aborted) or -> down (failed,
    interrupted: with the reason as the related fault) at its end."""
    what = "state-start" if starting else "state-end"
    key = message_key(batch.station, what, batch.batch_id)
    tx = transaction_id(batch.station, batch.batch_id)
    fault: Fault | None = None
    if starting:
        old, new, duration, at = SBY_NO_PRODUCT, PRD_REGULAR_WORK, None, batch.created_at
    else:
        at = batch.ended_at or batch.created_at
        old, duration = PRD_REGULAR_WORK, timespan((at - batch.created_at).total_seconds())
        new = USD if batch.state in ("failed", "interrupted") else SBY_NO_PRODUCT
        if new == USD:
            fault = {"TransactionID": tx, "Cause": "ProcessError", "Severity": "Error", "FaultCode": f"batch-{batch.state}",
                     "FaultOccurrenceId": name_uuid("fault", batch.station, batch.batch_id), "Lane": None, "Stage": None,
                     "SideLocation": "Unknown", "AccessType": "Unknown", "Description": batch.reason or batch.state,
                     "OccurredAt": iso_or_none(batch.ended_at)}
    body: StationStateChanged = {"OldState": old, "OldStateDuration": duration, "NewState": new, "RelatedFault": fault}
    return Outgoing(key, envelope(STATION_STATE_CHANGED, body, source, at, key))


def calibration_performed(batch: BatchFacts, source: str) -> Outgoing | None:
    """The reference thermometer's calibration in force, announced with the first batch that uses it
    (None: the batch's config had no thermometer). Keyed by the thermometer and its calibration's
    words, so a new certificate is a new message and the same one is not repeated per batch."""
    if batch.thermometer is None:
        return None
    words = batch.thermometer_calibration.strip()
    key = message_key(batch.station, "calibration", name_uuid("thermometer", batch.thermometer, words))
    body: CalibrationPerformed = {
        "TransactionID": transaction_id(batch.station, batch.batch_id),
        "Calibration": {
            "CalibrationCode": "REFERENCE_THERMOMETER", "CalibrationType": "General",
            "Comments": f"plate reference thermometer ({batch.thermometer}): "
                        + (words or "its calibration is not stated in the config ([certificate] reference_thermometer)"),
            "Status": "Ok" if words else "Unknown", "CalibrationTime": None, "Measurements": [],
        },
    }
    return Outgoing(key, envelope(CALIBRATION_PERFORMED, body, source, batch.created_at, key))


AXES = ("x", "y", "z")


def _measurements(v: VerdictFacts, key: str, result: TestResult) -> list[NumericMeasurement]:
    out: list[NumericMeasurement] = []
    for name, units, values in (("TDB", "mg/°C", v.tdb_mg_per_c), ("TDSF", "ppm/°C", v.tdsf_ppm_per_c)):
        for ax, value in zip(AXES, values):
            f = finite_or_none(value)
            if f is None:
                continue
            mname = f"{name}_{ax.upper()}"
            out.append({
                "$type": "CFX.Structures.NumericMeasurement, CFX", "UniqueIdentifier": name_uuid("measurement", key, mname),
                "MeasurementName": mname, "TimeRecorded": iso_or_none(v.judged_at), "Sequence": len(out) + 1,
                "Result": result, "CRDs": None,
                "MeasuredValue": {"Value": f, "ValueUnits": units, "ExpectedValue": None, "ExpectedValueUnits": None,
                                  "MinimumAcceptableValue": None, "MinimumAcceptableValueUnits": None,
                                  "MaximumAcceptableValue": None, "MaximumAcceptableValueUnits": None},
            })
    return out


def units_tested(batch: BatchFacts, v: VerdictFacts, temps: TempStats | None, source: str) -> Outgoing:
    """One verdict record of one unit: its slot as the position, its segment temperatures as the
    test's condition, its TDB/TDSF per axis as measurements, the verdict as the result."""
    key = message_key(batch.station, "units-tested", v.result_seq)
    result = test_result(v.verdict, v.route_check)
    conditions: list[TemperatureCondition] = []
    if temps is not None:
        conditions.append({"$type": "CFX.Structures.Temperature, CFX", "StartTime": iso_or_none(v.started_at),
                           "EndTime": iso_or_none(v.ended_at), "MeanValue": temps.mean_c, "MedianValue": temps.median_c,
                           "MaxValue": temps.max_c, "MinValue": temps.min_c})
    words = [f"verdict {v.verdict or 'none'}"]
    words += [f"grade {v.grade}"] if v.grade else []
    words += [f"tray {v.tray}"] if v.tray else []
    words += [f"attempt {v.attempt}", f"record revision {v.revision}"]
    if v.limits_name:
        words.append(f"limits {v.limits_name} {v.limits_version or ''}".rstrip())
    comments = ", ".join(words) + (f": {v.reason}" if v.reason else "")
    test: Test = {
        "UniqueIdentifier": name_uuid("test", key), "TestName": "THERMAL_CALIBRATION",
        "TestStartTime": iso_or_none(v.started_at), "TestEndTime": iso_or_none(v.ended_at),
        "TestConditions": conditions, "TestProcedure": batch.profile, "Comments": comments, "Result": result,
        "Error": (v.reason or "error") if result == "Error" else None, "SymptomsFound": [], "DefectsFound": [],
        "Measurements": _measurements(v, key, result),
    }
    body: UnitsTested = {
        "TransactionId": transaction_id(batch.station, batch.batch_id), "TestMethod": "Automated",
        "Tester": {"OperatorIdentifier": batch.operator, "ActorType": "Human", "LastName": None, "FirstName": None,
                   "LoginName": batch.operator} if batch.operator else None,
        "RecipeName": batch.profile, "RecipeRevision": None,
        "SamplingInformation": {"SamplingMethod": "NoSampling", "LotSize": None, "SampleSize": None},
        "TestedUnits": [{"UnitIdentifier": v.serial, "UnitPositionNumber": position_of(batch, v.slot),
                         "OverallResult": result, "Tests": [test]}],
    }
    return Outgoing(key, envelope(UNITS_TESTED, body, source, v.judged_at or batch.created_at, key))


__all__ = ["CFX_VERSION", "WORK_STARTED", "WORK_COMPLETED", "UNITS_TESTED", "STATION_STATE_CHANGED", "CALIBRATION_PERFORMED",
           "Envelope", "Outgoing", "VerdictFacts", "name_uuid", "transaction_id", "timespan", "default_handle", "message_key",
           "envelope", "work_started", "work_completed", "station_state_changed", "calibration_performed", "units_tested",
           "test_result", "work_result"]
