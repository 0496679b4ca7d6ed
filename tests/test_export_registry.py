"""An export format is one registered writer (station/records/export_formats.py).

A CSV writer defined here is registered in one place (the `csv_format` fixture) and, with no other
change, `station export csv` writes it and `GET /api/batches/{id}/export.csv` /
`GET /api/runs/{id}/export.csv` serve the same bytes with its media type and file name, documented
in the OpenAPI. Unregistered, the command line refuses the word and the REST path is a 404. The
built-in formats are the registry's too (STDF, OCPTV: tests/test_exports.py checks their bytes).
"""

from __future__ import annotations

import csv
import io
from types import SimpleNamespace

import httpx
import pytest

from cli.main import main
from contracts.events import DutVerdict, SlotStateChanged
from db import Database, DbWriter
from station.decisions.limits import Limit, ProductSpec
from station.decisions.verdicts import Measurement, decide
from station.records.export_formats import ExportFormat, export_formats, register, unregister
from station.records.export_model import ExportReport, load_report
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

TOKEN = "mes-token-export-registry"
SPEC = ProductSpec(name="ACC-3D", version="2026-07", sensor="LIS3DSH", guard_sigma=2.0,
                   limits=[Limit(measurement="tdb_mg_per_c", low=-1.5, high=1.5, unit="mg/C", label="TDB",
                                 required=True)])
DUTS = [("s01", "SN-P1", (0.21, -0.31, 0.11)), ("s02", "SN-F1", (2.41, 0.11, -0.21))]  # pass, fail (TDB x)


def write_csv(report: ExportReport) -> bytes:
    """The example format: one row per judged measurement."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["batch", "run", "serial", "verdict", "measurement", "axis", "value", "unit", "outcome"])
    for p in report.parts:
        for t in p.tests:
            w.writerow([report.batch_id, p.run_id, p.serial, p.verdict, t.name, t.axis or "", t.value, t.unit,
                        t.outcome])
    return out.getvalue().encode()


CSV = ExportFormat(name="csv", title="CSV table", media_type="text/csv", suffix="csv", write=write_csv,
                   help="one row per judged measurement")


@pytest.fixture
def csv_format():
    """The one place the example format is registered."""
    register(CSV)
    try:
        yield CSV
    finally:
        unregister(CSV.name)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("export_registry") / "station.db"
    db = Database(f"sqlite:///{path}", station="line-3")
    db.upgrade()
    batch = db.create_batch("fast-thermal", "alice", {"name": "line-3"}, state="running")
    w = DbWriter(db, interval_s=0.02)
    runs = {}
    for slot, serial, tdb in DUTS:
        runs[serial] = run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial, "sensor": "LIS3DSH"})
        w.bind_run(batch, slot, run)
        v = decide([Measurement("tdb_mg_per_c", b, "mg/C", ax, 0.013) for ax, b in zip("xyz", tdb)], SPEC,
                   state="done", fault_reason="", required=("tdb_mg_per_c",))
        w.submit(SlotStateChanged(batch, slot, serial, "done", ""))
        w.submit(DutVerdict(batch, slot, serial, verdict={**v.to_json(), "attempt": 1}))
    w.flush()
    db.set_batch_state(batch, "finished")
    running = db.create_batch("fast-thermal", "bob", {}, state="running")
    w.close()
    yield SimpleNamespace(db=db, path=path, batch=batch, runs=runs, running=running)
    db.dispose()


def serve(store):
    """The web app as the export tests build it (created after any registration, as a daemon's is)."""
    app = create_app(SimpleNamespace(config=None, bus=None, db=store.db), repo=DbRepository(store.db),
                     tokens=TokenStore([(TOKEN, "mes", "mes")]), outbox=False)
    return serve_in_thread(app)


def test_a_registered_format_is_served_by_the_cli_and_the_rest_route(store, csv_format, tmp_path, capsys):
    out = tmp_path / "batch.csv"
    assert main(["export", "csv", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"CSV table of batch {store.batch}: 2 parts (1 pass, 1 fail), 6 measurements" in said
    expected = write_csv(load_report(store.db, batch_id=store.batch))
    assert out.read_bytes() == expected
    rows = list(csv.DictReader(io.StringIO(expected.decode())))
    assert {(r["serial"], r["verdict"]) for r in rows} == {("SN-P1", "pass"), ("SN-F1", "fail")} and len(rows) == 6

    url, stop = serve(store)
    try:
        with httpx.Client(base_url=url, timeout=60, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            r = c.get(f"/api/batches/{store.batch}/export.csv")
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
            assert f'filename="batch-{store.batch}.csv"' in r.headers["content-disposition"]
            assert r.content == expected
            run = store.runs["SN-F1"]
            r = c.get(f"/api/runs/{run}/export.csv")
            assert r.status_code == 200 and f'filename="run-{run}.csv"' in r.headers["content-disposition"]
            assert {row["serial"] for row in csv.DictReader(io.StringIO(r.text))} == {"SN-F1"}
            # the same refusals as every format: running 409, unknown id 404, no token 401
            assert c.get(f"/api/batches/{store.running}/export.csv").status_code == 409
            assert c.get("/api/batches/999999/export.csv").status_code == 404
            assert httpx.get(f"{url}/api/batches/{store.batch}/export.csv").status_code == 401
            # and the OpenAPI documents it as it does the built-in ones
            paths = c.get("/openapi.json").json()["paths"]
            for path, name in ((f"/api/batches/{{batch_id}}/export.csv", "batch"),
                               (f"/api/runs/{{run_id}}/export.csv", "run")):
                op = paths[path]["get"]
                assert list(op["responses"]["200"]["content"]) == ["text/csv"], path
                assert op["tags"] == ["exports"] and "409" in op["responses"], path
            assert "/api/batches/{batch_id}/export.stdf" in paths and "/api/runs/{run_id}/export.ocptv.json" in paths
    finally:
        stop()


def test_the_cli_help_lists_every_registered_format(csv_format, capsys):
    with pytest.raises(SystemExit) as done:
        main(["export", "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "{stdf,ocptv,csv}" in text and "csv: one row per judged measurement" in text


def test_an_unregistered_format_is_unknown_to_the_cli_and_the_api(store, tmp_path, capsys):
    assert "csv" not in export_formats()
    with pytest.raises(SystemExit) as done:
        main(["export", "csv", "--batch", str(store.batch), "--db", str(store.path), "--out", str(tmp_path / "x")])
    assert done.value.code == 2 and "invalid choice: 'csv'" in capsys.readouterr().err
    url, stop = serve(store)
    try:
        with httpx.Client(base_url=url, timeout=60, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            assert c.get(f"/api/batches/{store.batch}/export.csv").status_code == 404
            assert c.get(f"/api/batches/{store.batch}/export.stdf").status_code == 200
    finally:
        stop()


def test_a_format_that_clashes_or_cannot_be_a_path_is_refused():
    with pytest.raises(ValueError, match="clashes"):
        register(ExportFormat(name="stdf", title="x", media_type="text/plain", suffix="txt", write=write_csv))
    with pytest.raises(ValueError, match="clashes"):
        register(ExportFormat(name="stdf2", title="x", media_type="text/plain", suffix="stdf", write=write_csv))
    with pytest.raises(ValueError, match="suffix"):
        ExportFormat(name="bad", title="x", media_type="text/plain", suffix="a/b", write=write_csv)
    with pytest.raises(ValueError, match="name"):
        ExportFormat(name="Bad Name", title="x", media_type="text/plain", suffix="bad", write=write_csv)
    assert list(export_formats()) == ["stdf", "ocptv"]
