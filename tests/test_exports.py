"""Exports for yield and traceability tools (docs/exports.md): STDF V4 and OCP Test & Validation JSON
of a stored batch, through the CLI and REST.

The batch is judged by the station's own decide() (pass grade A, pass grade B, fail, marginal, a
faulted DUT with no checks, a DUT with a required measurement missing) and stored through the real
DbWriter with work order, part number, revision, lot and label serials. Independent truth: the
dut_run rows read straight from the database, Semi-ATE-STDF's reader for the STDF bytes, and the
OCPTV spec's published JSON schema (tests/data/ocptv_output_schema.json) for every JSON line. The
mutation tests change one flag, limit or type in an export and show the same checks then fail
(readers and checks: tests/exports_support.py).
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import httpx
import pytest

from contracts.events import DutVerdict, SlotStateChanged
from contracts.trace import Trace
from db import Database, DbWriter
from exports_support import (check_ocptv, check_stdf, db_truth, load_validator, mutate, read_ocptv,
                             read_stdf, rewrite, set_at)
from cli.main import main
from station.decisions.limits import Grade, Limit, ProductSpec
from station.decisions.verdicts import Measurement, decide
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

TOKEN = "mes-token-exports"
TRACE = dict(work_order="WO-2026-0042", part_number="ACC-3D-100", part_revision="C", lot="L2407-15")

SPEC = ProductSpec(
    name="ACC-3D", version="2026-07", sensor="LIS3DSH", guard_sigma=2.0,
    limits=[Limit(measurement="tdb_mg_per_c", low=-1.5, high=1.5, unit="mg/C", label="TDB", required=True),
            Limit(measurement="tdsf_ppm_per_c", low=-500.0, high=500.0, unit="ppm/C", label="TDSF", required=True),
            Limit(measurement="drift_error_mg", high=2.0, unit="mg", label="drift error", required=True)],
    grades=[Grade(name="A", tray="T-A", limits=[Limit(measurement="tdb_mg_per_c", low=-1.0, high=1.0, unit="mg/C")]),
            Grade(name="B", tray="T-B")])


def measurements(tdb, tdsf, drift) -> list[Measurement]:
    out = []
    for ax, b, s, d in zip("xyz", tdb, tdsf, drift):
        out.append(Measurement("tdb_mg_per_c", b, "mg/C", ax, 0.013))
        out.append(Measurement("tdsf_ppm_per_c", s, "ppm/C", ax, 2.1))
        if d is not None:
            out.append(Measurement("drift_error_mg", d, "mg", ax, 0.07))
    return out


# slot, serial, end state, fault reason, (tdb, tdsf, drift) -> the verdict decide() gives
DUTS = [
    ("s01", "SN-P1", "done", "", ((0.2137, -0.3141, 0.1123), (-121.7, 80.3, 33.9), (0.41, 0.52, 0.63))),  # pass A
    ("s02", "SN-F1", "done", "", ((2.4173, 0.11, -0.21), (-50.1, 12.2, 8.8), (0.5, 0.5, 0.5))),  # fail: TDB x
    ("s03", "SN-M1", "done", "", ((0.3, 1.4911, 0.1), (10.0, 20.0, 30.0), (0.4, 0.4, 0.4))),  # marginal: TDB y
    ("s04", "SN-E1", "faulted", "serial link lost after 3 retries", None),  # error, no checks
    ("s05", "SN-E2", "done", "", ((0.1, 0.2, 0.3), (1.0, 2.0, 3.0), (0.3, 0.3, None))),  # error: drift z missing
    ("s06", "SN-P2", "done", "", ((1.2345, 0.05, -0.07), (99.9, -99.9, 0.1), (1.1, 1.2, 1.3))),  # pass B
]
EXPECTED = {"SN-P1": ("pass", "A"), "SN-F1": ("fail", "reject"), "SN-M1": ("marginal", "hold"),
            "SN-E1": ("error", "retest"), "SN-E2": ("error", "retest"), "SN-P2": ("pass", "B")}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("exports") / "station.db"
    db = Database(f"sqlite:///{path}", station="line-3")
    db.upgrade()
    labels = {slot: f"LBL-{serial}" for slot, serial, *_ in DUTS if serial != "SN-E2"}  # s05: no label scanned
    batch = db.create_batch("fast-thermal", "alice", {"name": "line-3"}, state="running",
                            trace=Trace(**TRACE, labels=labels))
    w = DbWriter(db, interval_s=0.02)
    for slot, serial, state, fault, values in DUTS:
        run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial, "sensor": "LIS3DSH", "fw": "2.3.1"})
        w.bind_run(batch, slot, run)
        v = decide(measurements(*values) if values else [], SPEC, state=state, fault_reason=fault,
                   required=("tdb_mg_per_c", "tdsf_ppm_per_c", "drift_error_mg"))
        w.submit(SlotStateChanged(batch, slot, serial, state, fault))
        w.submit(DutVerdict(batch, slot, serial, verdict={**v.to_json(), "attempt": 1}))
    w.flush()
    db.set_batch_state(batch, "finished")
    running = db.create_batch("fast-thermal", "bob", {}, state="running", trace=Trace(**TRACE))
    running_run = db.create_run(running, "s01", "SN-R1", "LIS3DSH", {"serial": "SN-R1"}, state="running")
    w.close()
    yield SimpleNamespace(db=db, path=path, batch=batch, running=running, running_run=running_run)
    db.dispose()


def test_the_batch_holds_every_kind_of_verdict(store):
    _, runs = db_truth(store.db, store.batch)
    assert {s: (r["verdict"], r["grade"]) for s, r in runs.items()} == EXPECTED
    assert runs["SN-E1"]["checks"] == [] and runs["SN-E1"]["state"] == "faulted"
    assert [c["value"] for c in runs["SN-E2"]["checks"] if c["value"] is None] == [None]


# ---------------------------------------------------------------------------------------- STDF
def test_an_unjudged_run_of_an_ended_batch_is_a_failing_part_never_a_pass(validator):
    """Pure core: a run never judged (its batch was interrupted) or with a word the station does not
    use leaves as `error` with why, in the failing bin, in both formats."""
    from station.records.export_model import build_report
    from station.records.export_ocptv import write_ocptv
    from station.records.export_stdf import write_stdf

    batch = {"id": 7, "state": "interrupted", "created_at": "2026-05-01T08:00:00+00:00", **TRACE}
    runs = [{"id": 70, "slot": "s02", "serial": "U1", "state": "interrupted", "verdict": None, "fault_reason": "power cut"},
            {"id": 71, "slot": "s01", "serial": "U2", "state": "done", "verdict": "passed", "grade": "A",
             "verdict_detail": {"checks": [{"measurement": "bow_mg", "axis": "x", "value": float("nan"), "unit": "mg",
                                            "high": 1.0, "outcome": "pass"}]}}]
    report = build_report(batch, runs)
    u1, u2 = report.parts
    assert (u1.verdict, u1.hard_bin, u1.site, u1.reason) == ("error", 4, 2, "not judged: run interrupted (power cut)")
    assert (u2.verdict, u2.hard_bin, u2.site) == ("error", 4, 1) and "unknown verdict 'passed'" in u2.reason
    assert [(t.value, t.outcome) for t in u2.tests] == [(None, "error")]  # NaN is no measurement
    prrs = {p["prr"]["PART_ID"]: p["prr"] for p in read_stdf(write_stdf(report))["parts"]}
    assert all(int("".join(p["PART_FLG"]), 2) & 0x08 and p["HARD_BIN"] == 4 for p in prrs.values())
    outputs = read_ocptv(write_ocptv(report), validator)  # every line valid OCPTV
    assert [(o["testRunEnd"]["result"], o["diagnosis"]["type"]) for o in outputs] == [("NOT_APPLICABLE", "FAIL"),
                                                                                     ("FAIL", "FAIL")]


def cli(*args: str) -> int:
    return main(["export", *args])


def test_stdf_of_the_batch_through_the_cli_reads_back_as_the_database_says(store, tmp_path, capsys):
    out = tmp_path / "batch.stdf"
    assert cli("stdf", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)) == 0
    assert "6 parts (2 pass, 1 marginal, 1 fail, 2 error)" in capsys.readouterr().out
    check_stdf(out.read_bytes(), store.db, store.batch)
    soft = {p["prr"]["PART_ID"]: p["prr"]["SOFT_BIN"] for p in read_stdf(out.read_bytes())["parts"]}
    assert (soft["SN-P1"], soft["SN-P2"], soft["SN-F1"], soft["SN-M1"], soft["SN-E1"]) == (101, 102, 301, 201, 401)


def test_stdf_of_one_faulted_run_is_a_failing_part_without_tests(store, tmp_path):
    _, runs = db_truth(store.db, store.batch)
    out = tmp_path / "run.stdf"
    assert cli("stdf", "--run", str(runs["SN-E1"]["id"]), "--db", str(store.path), "--out", str(out)) == 0
    check_stdf(out.read_bytes(), store.db, store.batch, serials={"SN-E1"})
    (part,) = read_stdf(out.read_bytes())["parts"]
    assert "serial link lost" in part["prr"]["PART_TXT"] and part["ptr"] == []


@pytest.mark.parametrize("kind,pick,field,value", [
    ("PRR", lambda d: d["PART_ID"] == "SN-F1", "PART_FLG", 0),  # a failed part flagged passed
    ("PRR", lambda d: d["PART_ID"] == "SN-E1", "HARD_BIN", 1),  # a faulted part in the good bin
    ("PTR", lambda d: d["TEST_TXT"] == "tdb_mg_per_c x", "HI_LIMIT", 1.6),  # a wrong limit
    ("PTR", lambda d: d["TEST_TXT"] == "drift_error_mg y", "UNITS", "ug"),  # a wrong unit
    ("PTR", lambda d: d["TEST_TXT"] == "tdsf_ppm_per_c z", "RESULT", 31.0),  # a wrong value
    ("MIR", lambda d: True, "SBLOT_ID", "WO-1"),  # another work order
])
def test_a_mutated_stdf_fails_the_same_check(store, tmp_path, kind, pick, field, value):
    out = tmp_path / "batch.stdf"
    assert cli("stdf", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)) == 0
    check_stdf(out.read_bytes(), store.db, store.batch)
    mutated = rewrite(out.read_bytes(), kind, pick, field, value)  # outside raises: must not fail itself
    assert mutated != out.read_bytes()
    with pytest.raises(AssertionError):
        check_stdf(mutated, store.db, store.batch)


# ---------------------------------------------------------------------------------------- OCPTV
@pytest.fixture(scope="module")
def validator():
    return load_validator()


def test_ocptv_of_the_batch_through_the_cli_validates_and_says_what_the_database_says(store, tmp_path, validator):
    out = tmp_path / "batch.ocptv.json"
    assert cli("ocptv", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)) == 0
    check_ocptv(out.read_bytes(), validator, store.db, store.batch)


@pytest.mark.parametrize("serial,change", [
    ("SN-F1", set_at(["testStepArtifact", "diagnosis", "type"], "PASS")),  # a failed part diagnosed PASS
    ("SN-E1", set_at(["testRunArtifact", "testRunEnd", "result"], "PASS")),  # not a valid pair, and a pass
    ("SN-P1", set_at(["testStepArtifact", "measurement", "validators"], [{"type": "LESS_THAN_OR_EQUAL", "value": 1.6}])),
    ("SN-M1", set_at(["testStepArtifact", "measurement", "unit"], "g")),  # a wrong unit
    ("SN-P2", set_at(["testRunArtifact", "testRunStart", "dutInfo", "metadata"], {})),  # the label serial lost
])
def test_a_mutated_ocptv_fails_the_same_check(store, tmp_path, validator, serial, change):
    out = tmp_path / "batch.ocptv.json"
    assert cli("ocptv", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)) == 0
    check_ocptv(out.read_bytes(), validator, store.db, store.batch)
    mutated = mutate(out.read_bytes(), serial, change)  # outside raises: must not fail itself
    with pytest.raises(AssertionError):
        check_ocptv(mutated, validator, store.db, store.batch)


def test_the_schema_refuses_what_the_spec_does_not_allow(store, tmp_path, validator):
    out = tmp_path / "run.ocptv.json"
    _, runs = db_truth(store.db, store.batch)
    assert cli("ocptv", "--run", str(runs["SN-F1"]["id"]), "--db", str(store.path), "--out", str(out)) == 0
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert all(validator.is_valid(x) for x in lines)
    m = next(x for x in lines if "measurement" in x.get("testStepArtifact", {}))
    for broken in ({**m, "extra": 1}, {**m, "testStepArtifact": {"testStepId": "0", "measurement": {"value": 1.0}}},
                   {**m, "sequenceNumber": -1}):
        assert not validator.is_valid(broken)


def test_the_bundled_schema_accepts_the_reference_writers_output(validator):
    """The schema under tests/data was assembled from the spec's files: the `ocptv` package (the
    spec's Python reference writer) must produce lines it accepts, for every artifact kind the export
    uses, and its dutInfo/measurement/diagnosis keys must be the ones the export writes."""
    import ocptv.output as tv
    from ocptv.output import (DiagnosisType, SoftwareType, Subcomponent, SubcomponentType, TestResult, TestStatus,
                              Validator, ValidatorType)

    lines: list[str] = []

    class Capture(tv.Writer):
        def write(self, buffer: str) -> None:
            lines.append(buffer)

    tv.config(writer=Capture())
    try:
        dut = tv.Dut(id="run-1", name="SN-P1")
        dut.add_platform_info("LIS3DSH")
        dut.add_software_info(name="firmware", type=SoftwareType.FIRMWARE, version="2.3.1")
        hw = dut.add_hardware_info(name="LIS3DSH", serial_no="SN-P1", part_no="ACC-3D-100", revision="C", location="s01")
        run = tv.TestRun(name="fast-thermal", version="0.1.0", parameters={"batch_id": 1}, command_line="")
        run.start(dut=dut)
        step = run.add_step("fast-thermal")
        step.start()
        step.add_measurement(name="tdb_mg_per_c", value=0.2137, unit="mg/C", hardware_info=hw,
                             validators=[Validator(type=ValidatorType.GREATER_THAN_OR_EQUAL, value=-1.5, name="low limit"),
                                         Validator(type=ValidatorType.LESS_THAN_OR_EQUAL, value=1.5, name="high limit")],
                             subcomponent=Subcomponent(name="x", type=SubcomponentType.ASIC_SUBSYSTEM),
                             metadata=tv.Metadata({"outcome": "pass"}))
        step.add_error(symptom="not-measured", message="z drift error not measured")
        step.add_diagnosis(DiagnosisType.UNKNOWN, verdict="marginal", message="grade hold", hardware_info=hw)
        step.end(status=TestStatus.ERROR)
        run.end(status=TestStatus.ERROR, result=TestResult.NOT_APPLICABLE)
    finally:
        tv.config(writer=tv.StdoutWriter())
    objs = [json.loads(x) for x in lines]
    assert len(objs) == 8 and all(validator.is_valid(o) for o in objs), [e.message for o in objs
                                                                         for e in validator.iter_errors(o)]
    ref_dut = objs[1]["testRunArtifact"]["testRunStart"]["dutInfo"]
    assert set(ref_dut["hardwareInfos"][0]) >= {"hardwareInfoId", "name", "serialNumber", "partNumber", "revision",
                                                 "location"}
    ref_m = objs[3]["testStepArtifact"]["measurement"]
    assert set(ref_m) == {"name", "value", "unit", "validators", "hardwareInfoId", "subcomponent", "metadata"}


# ---------------------------------------------------------------------------------------- REST and refusals
@pytest.fixture(scope="module")
def web(store):
    app = create_app(SimpleNamespace(config=None, bus=None, db=store.db), repo=DbRepository(store.db),
                     tokens=TokenStore([(TOKEN, "mes", "mes")]), outbox=False)
    url, stop = serve_in_thread(app)
    with httpx.Client(base_url=url, timeout=60, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
        yield c
    stop()


def test_rest_serves_the_same_exports_as_the_cli(store, web, tmp_path, validator):
    out = tmp_path / "cli.stdf"
    assert cli("stdf", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)) == 0
    r = web.get(f"/api/batches/{store.batch}/export.stdf")
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    assert f'filename="batch-{store.batch}.stdf"' in r.headers["content-disposition"]
    assert r.content == out.read_bytes()
    check_stdf(r.content, store.db, store.batch)
    r = web.get(f"/api/batches/{store.batch}/export.ocptv.json")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/x-ndjson")
    check_ocptv(r.content, validator, store.db, store.batch)
    _, runs = db_truth(store.db, store.batch)
    r = web.get(f"/api/runs/{runs['SN-M1']['id']}/export.stdf")
    assert r.status_code == 200
    check_stdf(r.content, store.db, store.batch, serials={"SN-M1"})
    r = web.get(f"/api/runs/{runs['SN-P1']['id']}/export.ocptv.json")
    assert r.status_code == 200 and len(read_ocptv(r.content, validator)) == 1


def test_running_answers_409_unknown_404_no_token_401(store, web, capsys):
    for path in (f"/api/batches/{store.running}/export.stdf", f"/api/batches/{store.running}/export.ocptv.json",
                 f"/api/runs/{store.running_run}/export.stdf", f"/api/runs/{store.running_run}/export.ocptv.json"):
        r = web.get(path)
        assert r.status_code == 409, path
        assert "not final" in r.json()["detail"] or "not judged" in r.json()["detail"], path
    for path in ("/api/batches/999999/export.stdf", "/api/runs/999999/export.ocptv.json"):
        r = web.get(path)
        assert r.status_code == 404 and "not found" in r.json()["detail"], path
    assert web.get("/api/batches/0/export.stdf").status_code == 422
    assert httpx.get(f"{web.base_url}/api/batches/{store.batch}/export.stdf").status_code == 401
    assert cli("stdf", "--batch", str(store.running), "--db", str(store.path), "--out", "/dev/null") == 2
    assert "not final" in capsys.readouterr().err
    assert cli("ocptv", "--run", "999999", "--db", str(store.path), "--out", "/dev/null") == 2
    assert "no run 999999" in capsys.readouterr().err
