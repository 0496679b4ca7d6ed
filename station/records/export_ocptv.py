"""OCP Test & Validation (OCPTV) output, spec version 2.0, of an export report (docs/exports.md).

One testRun per DUT run: the spec's testRunStart carries one dutInfo, so a run is the unit a
consumer files under a serial. A batch export is the runs' outputs one after the other in one
line-delimited JSON file; each begins with its own schemaVersion artifact (sequenceNumber 0), which
is where a reader splits it.

Written here as JSON lines rather than through the `ocptv` package (0.1.7), which is built for a
diagnostic emitting live: it stamps every artifact with the clock at the moment it is emitted
(time.time() inside its emitter, no way to pass a time) and sends it through a process-wide writer
(`ocptv.config(writer=...)`), so an export of a stored batch would carry the export's time instead of
when each DUT was tested, and two exports served at once would share one writer. The artifacts below
follow the spec's JSON schema (ocp-diag-core json_spec/output); the tests validate every line
against it and check that the package's own output validates against the same schema.

Per run:
    schemaVersion             2.0
    testRunStart              name = profile, version = station software, parameters (batch, run,
                              slot, attempt, station, operator, trace fields, limits), dutInfo:
                              serial (name, hardwareInfo.serialNumber), part number and revision,
                              slot (location), sensor (platformInfo), firmware (softwareInfo),
                              label serial (metadata)
    testStepStart             one step per run, named after the profile
    measurement               per check with a value: name, value, unit, validators (low: >=,
                              high: <=), axis as subcomponent, outcome/sigma/reason in metadata
    error                     per check with no value (not measured), and for a run that did not end
                              done (faulted, interrupted): its fault reason
    diagnosis                 the verdict: PASS only for pass; marginal UNKNOWN; fail, error FAIL
    testStepEnd, testRunEnd   COMPLETE (run done; result PASS for pass, FAIL otherwise) or ERROR
                              (run faulted/interrupted; result NOT_APPLICABLE, the spec's only pair)
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from typing import Any, Iterator

from station.records.export_model import ExportPart, ExportReport, ExportTest

SCHEMA_VERSION = {"major": 2, "minor": 0}
DIAGNOSIS_TYPE = {"pass": "PASS", "marginal": "UNKNOWN", "fail": "FAIL", "error": "FAIL"}
HW_ID = "dut"
FW_ID = "firmware"
STEP_ID = "0"


def ocptv_time(t: datetime | None) -> str:
    """RFC 3339 in UTC with Z, as the spec's examples and the ocptv package write it."""
    t = t or datetime.fromtimestamp(0, timezone.utc)
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return t.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def _clean(d: dict) -> dict:
    """Leave out empty optional fields (the schema types them as strings: no nulls)."""
    return {k: v for k, v in d.items() if v is not None and v != ""}


def dut_info(report: ExportReport, part: ExportPart) -> dict:
    hardware = _clean({"hardwareInfoId": HW_ID, "name": part.sensor or "accelerometer board",
                       "serialNumber": part.serial, "partNumber": report.part_number,
                       "revision": report.part_revision, "location": part.slot})
    info: dict[str, Any] = {"dutInfoId": f"run-{part.run_id}", "name": part.serial, "hardwareInfos": [hardware]}
    if part.sensor:
        info["platformInfos"] = [{"info": part.sensor}]
    if part.firmware:
        info["softwareInfos"] = [{"softwareInfoId": FW_ID, "name": "firmware", "version": part.firmware,
                                  "softwareType": "FIRMWARE"}]
    info["metadata"] = _clean({"label_serial": part.label_serial, "lot": report.lot,
                               "work_order": report.work_order})
    return info


def parameters(report: ExportReport, part: ExportPart) -> dict:
    return _clean({"batch_id": report.batch_id, "run_id": part.run_id, "slot": part.slot, "attempt": part.attempt,
                   "station": report.station, "operator": report.operator, "profile": report.profile,
                   "work_order": report.work_order, "part_number": report.part_number,
                   "part_revision": report.part_revision, "lot": report.lot, "limits_name": part.limits_name,
                   "limits_version": part.limits_version, "replay_of": report.replay_of})


def measurement(test: ExportTest) -> dict:
    validators = []
    if test.low is not None:
        validators.append({"name": "low limit", "type": "GREATER_THAN_OR_EQUAL", "value": test.low})
    if test.high is not None:
        validators.append({"name": "high limit", "type": "LESS_THAN_OR_EQUAL", "value": test.high})
    out: dict[str, Any] = {"name": test.name, "value": test.value, "unit": test.unit, "validators": validators,
                           "hardwareInfoId": HW_ID}
    if test.axis:
        out["subcomponent"] = {"type": "ASIC-SUBSYSTEM", "name": test.axis}
    out["metadata"] = _clean({"outcome": test.outcome, "sigma": test.sigma, "reason": test.reason,
                              "stdf_test_number": test.test_number})
    return out


def diagnosis(part: ExportPart) -> dict:
    message = f"grade {part.grade or '-'}, tray {part.tray or '-'}"
    if part.reason:
        message += f": {part.reason}"
    return {"verdict": part.verdict, "type": DIAGNOSIS_TYPE[part.verdict], "message": message, "hardwareInfoId": HW_ID}


def run_artifacts(report: ExportReport, part: ExportPart) -> Iterator[tuple[datetime | None, dict]]:
    """(time, artifact body) of one DUT run, in output order."""
    start = part.started_at or report.created_at
    judged = part.judged_at or part.ended_at or start
    end = part.ended_at or judged
    if judged is not None and end is not None and end < judged:
        end = judged  # judged after the run ended: the run's output ends with its verdict
    yield start, {"schemaVersion": dict(SCHEMA_VERSION)}
    yield start, {"testRunArtifact": {"testRunStart": {
        "name": report.profile or "thermal-cal", "version": report.software_version or "0",
        "commandLine": "", "parameters": parameters(report, part), "dutInfo": dut_info(report, part),
        "metadata": _clean({"station": report.station, "operator": report.operator, "scope": report.scope})}}}
    step = {"testStepId": STEP_ID}
    yield start, {"testStepArtifact": {**step, "testStepStart": {"name": report.profile or "calibration"}}}
    for test in part.tests:
        if test.value is None:
            body = {"symptom": "not-measured", "message": test.reason or f"{test.label} not measured"}
            yield judged, {"testStepArtifact": {**step, "error": body}}
        else:
            yield judged, {"testStepArtifact": {**step, "measurement": measurement(test)}}
    if not part.completed:
        body = {"symptom": f"run-{part.state or 'unknown'}", "message": part.reason or f"run {part.state}"}
        yield end, {"testStepArtifact": {**step, "error": body}}
    yield judged, {"testStepArtifact": {**step, "diagnosis": diagnosis(part)}}
    status = "COMPLETE" if part.completed else "ERROR"
    result = ("PASS" if part.passed else "FAIL") if part.completed else "NOT_APPLICABLE"
    yield end, {"testStepArtifact": {**step, "testStepEnd": {"status": status}}}
    yield end, {"testRunArtifact": {"testRunEnd": {"status": status, "result": result}}}


def write_ocptv(report: ExportReport) -> bytes:
    """Line-delimited JSON: every run's output, one artifact per line."""
    lines = []
    for part in report.parts:
        for seq, (t, body) in enumerate(run_artifacts(report, part)):
            lines.append(json.dumps({**body, "sequenceNumber": seq, "timestamp": ocptv_time(t)},
                                    separators=(",", ":"), allow_nan=False, ensure_ascii=False))
    return ("\n".join(lines) + "\n").encode() if lines else b""


__all__ = ["write_ocptv", "run_artifacts", "ocptv_time", "DIAGNOSIS_TYPE"]
