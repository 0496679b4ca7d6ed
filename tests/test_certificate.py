"""Calibration certificate (issues 13, 22): the pure core from stored rows, its ordering of the
checks (worst first) and its split over pages, the PDF through the CLI and REST, read back with
poppler (pdftotext for the words, pdftoppm renders it to a PNG in artifacts/). A verified run with
every check of its verdict: tests/test_certificate_pdf.py."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest

from db import Database
from db import repository as repo
from records_support import write_batches, write_unjudged
from station.records.certificate import build_certificate, certificate_for, certificate_id, ordered_checks
from station.records.certificate_layout import (BODY_BOTTOM_IN, BODY_TOP_IN, CHECK_COLUMNS_IN, ROW_HEIGHT_IN, Row, layout,
                                                paginate)
from station.records.certificate_pdf import render_pdf
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = ROOT / "artifacts"
TOKEN = "operator-token-certificate"
poppler = pytest.mark.skipif(shutil.which("pdftotext") is None or shutil.which("pdftoppm") is None,
                             reason="poppler-utils (pdftotext, pdftoppm) not installed")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("cert") / "station.db"
    db = Database(f"sqlite:///{path}", station="line-7")
    db.upgrade()
    written = write_batches(db, n_batches=1, per_batch=3, operator="alice")
    write_unjudged(db)
    yield db, path, written
    db.dispose()


def pdf_text(pdf: Path) -> str:
    return subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True, check=True).stdout


def test_pure_core_from_rows():
    run = {"id": 9, "batch_id": 2, "serial": "X1", "identity": {"sensor": "ADXL355", "fw": "1.0"}, "attempt": 2,
           "verdict": "marginal", "grade": "hold", "limits_name": "ADXL355", "limits_version": "3",
           "thermal_method": "offline",
           "thermal_by_method": {"offline": {"x": {"tdb_mg_per_c": 0.5, "tdb_sigma_mg_per_c": 0.02, "tdsf_ppm_per_c": 0.0,
                                                   "tdsf_clamped": True}}},
           "verdict_detail": {"checks": [{"measurement": "TDB", "axis": "x", "value": 0.5, "outcome": "marginal"}]}}
    segs = [{"temp_mean_c": 30.0, "acc_mean_g": [0.5, 0.5, 0.7], "orientation": 1}, {"temp_mean_c": None}]
    c = build_certificate(run, {"station": "s9", "operator": "op", "profile": "fast-thermal"}, segs)
    assert (c.serial, c.sensor, c.firmware, c.station, c.operator, c.attempt) == ("X1", "ADXL355", "1.0", "s9", "op", 2)
    tdb = c.coefficient("TDB", "x")
    assert (tdb.value, tdb.sigma, tdb.unit, tdb.method) == (0.5, 0.02, "mg/°C", "offline")
    assert "clamped" in c.coefficient("TDSF", "x").note
    assert len(c.fit_points) == 1 and c.checks[0]["outcome"] == "marginal"
    # no [certificate] in the stored config: nothing is made up
    assert (c.issuer.issuer, c.issuer.authorised_by, c.certificate_id) == ("", "", "s9-run9-unjudged")
    text = " ".join(" ".join(r.cells) for page in layout(c) for r in page)
    assert "Issued by not configured" in text and "Authorised by: not configured" in text
    assert "No plate reference thermometer was configured" in text
    assert "Work order / lot not recorded / not recorded" in text and "Label serial not scanned" in text
    # the trace of the batch and the run's label serial are printed (issue 24)
    c = build_certificate({**run, "label_serial": "X1"}, {"station": "s9", "operator": "op", "profile": "fast-thermal",
                                                          "work_order": "WO-7", "part_number": "ACC-1",
                                                          "part_revision": "B", "lot": "L3"}, segs)
    text = " ".join(" ".join(r.cells) for page in layout(c) for r in page)
    assert "Part / revision ACC-1 / B" in text and "Work order / lot WO-7 / L3" in text and "Label serial X1" in text


def test_certificate_id_names_station_run_and_revision():
    assert certificate_id("line-1 thermal station", 5, 2) == "line-1-thermal-station-run5-rev2"
    assert certificate_id("line-1 thermal station", 5, 3) != certificate_id("line-1 thermal station", 5, 2)
    assert certificate_id("s", 5, None) == "s-run5-unjudged"


def test_checks_worst_first_then_verdict_order():
    checks = [{"measurement": f"m{i}", "outcome": o} for i, o in enumerate(
        ["pass", "fail", "marginal", "pass", "error", "fail", "odd", "marginal", "pass"])]
    got = [(c["outcome"], c["measurement"]) for c in ordered_checks(checks + ["not a check"])]
    assert got == [("error", "m4"), ("fail", "m1"), ("fail", "m5"), ("marginal", "m2"), ("marginal", "m7"),
                   ("pass", "m0"), ("pass", "m3"), ("pass", "m8"), ("odd", "m6")]  # unknown last, never dropped


def _many_checks(n: int) -> list[dict]:
    outcomes = ["pass"] * 7 + ["marginal", "pass", "fail"]
    return [{"measurement": f"check_{i:03d}", "axis": "xyz"[i % 3], "value": 0.1 * i, "sigma": 0.01, "unit": "mg",
             "low": None, "high": 5.0, "outcome": outcomes[i % len(outcomes)]} for i in range(n)]


def test_every_check_on_some_page_worst_first_pages_never_overfull():
    checks = _many_checks(130)
    run = {"id": 3, "batch_id": 1, "serial": "P1", "identity": {"sensor": "LIS3DSH"}, "verdict": "fail",
           "verdict_detail": {"checks": checks}}
    cert = build_certificate(run, {"station": "s"}, [])
    pages = layout(cert)
    usable = BODY_BOTTOM_IN - BODY_TOP_IN
    rows = [(n, r) for n, page in enumerate(pages, 1) for r in page
            if r.table == CHECK_COLUMNS_IN and r.kind == "table_row"]
    # every check once, in the certificate's order: all fails, then marginals, then passes
    assert [r.cells[1] for _n, r in rows] == [c["measurement"] for c in cert.checks]
    assert sorted(c["measurement"] for c in cert.checks) == sorted(c["measurement"] for c in checks)
    assert [r.cells[0] for _n, r in rows] == ["FAIL"] * 13 + ["MARGINAL"] * 13 + ["PASS"] * 104
    assert rows[0][0] == 1  # the worst check is on page 1
    assert len({n for n, _r in rows}) >= 3 and len(pages) >= 4
    for n, page in enumerate(pages, 1):
        assert sum(r.height_in for r in page) <= usable + 1e-9, n
        assert page[0].kind != "gap" and not page[-1].keep, n  # no gap on top, no heading at the bottom
        if n > 1 and any(r.table == CHECK_COLUMNS_IN and r.kind == "table_row" for r in page):
            assert page[0].cells == ("Checks against the limits (continued)",) and page[1].kind == "table_head", n
    # a page of checks only holds as many rows as its height takes below the repeated header
    fit = int((usable - ROW_HEIGHT_IN["heading"] - ROW_HEIGHT_IN["table_head"]) // ROW_HEIGHT_IN["table_row"])
    continued = ("Checks against the limits (continued)",)
    only_checks = [p for p, nxt in zip(pages[1:], pages[2:]) if nxt[0].cells == continued]
    assert only_checks and all(len(p) == 2 + fit for p in only_checks)


def test_paginate_measures_rows_per_page():
    usable = BODY_BOTTOM_IN - BODY_TOP_IN
    per_page = int(usable // ROW_HEIGHT_IN["text"] + 1e-9)
    pages = paginate([Row("text", (f"line {i}",)) for i in range(3 * per_page + 5)])
    assert [len(p) for p in pages] == [per_page, per_page, per_page, 5]
    head = Row("table_head", ("h",), table=(1.0,))
    cont = (Row("heading", ("T (continued)",), keep=True), head)
    rows = [Row("heading", ("T",), keep=True), Row("table_head", ("h",), table=(1.0,), keep=True)]
    rows += [Row("table_row", (str(i),), table=(1.0,), cont=cont) for i in range(200)]
    pages = paginate(rows)
    assert [r.cells[0] for p in pages for r in p if r.kind == "table_row"] == [str(i) for i in range(200)]
    assert all(p[0].cells == ("T (continued)",) and p[1] is head for p in pages[1:])


@poppler
def test_cli_writes_certificate_pdf_with_serial_verdict_coefficients(store, tmp_path):
    db, path, written = store
    w = written[0]
    out = tmp_path / "cert.pdf"
    r = subprocess.run([sys.executable, "-m", "cli", "certificate", w["serial"], "--db", str(path), "--out", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert out.read_bytes().startswith(b"%PDF")
    text = pdf_text(out)
    run = repo.run_detail(db, w["run"])
    assert w["serial"] in text and "line-7" in text and "alice" in text and "2.3.1" in text
    assert f"Verdict {run['verdict'].upper()}" in text and "LIS3DSH version 2026-11" in text
    for ax, b, s in zip("xyz", w["tdb"], w["tdsf"]):
        assert f"{b:+.4g} ± " in text, (ax, b)
        assert f"{s:+.4g} ± " in text, (ax, s)
    assert "mg/°C" in text and "ppm/°C" in text
    ARTIFACTS.mkdir(exist_ok=True)
    subprocess.run(["pdftoppm", "-png", "-r", "70", "-singlefile", str(out), str(ARTIFACTS / "certificate")], check=True)
    png = ARTIFACTS / "certificate.png"
    assert png.stat().st_size > 20_000  # a page with a table and three plots, not a blank page
    # unknown serial: one line, exit 2
    r = subprocess.run([sys.executable, "-m", "cli", "certificate", "NOPE", "--db", str(path)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 2 and "no DUT with serial 'NOPE'" in r.stderr and "Traceback" not in r.stderr


@poppler
def test_rest_certificate_pdf_and_404(store, tmp_path):
    db, _path, written = store
    app = create_app(SimpleNamespace(config=None, bus=None, db=db), repo=DbRepository(db),
                     tokens=TokenStore([(TOKEN, "operator", "op")]), outbox=False)
    url, stop_server = serve_in_thread(app)
    try:
        h = {"Authorization": f"Bearer {TOKEN}"}
        with httpx.Client(base_url=url, timeout=60, headers=h) as c:
            serial = written[1]["serial"]
            r = c.get(f"/api/duts/{serial}/certificate.pdf")
            assert r.status_code == 200 and r.headers["content-type"] == "application/pdf"
            (tmp_path / "r.pdf").write_bytes(r.content)
            text = pdf_text(tmp_path / "r.pdf")
            assert serial in text and f"Verdict {written[1]['verdict'].upper()}" in text
            r = c.get("/api/duts/UNKNOWN-9/certificate.pdf")
            assert r.status_code == 404 and r.json()["detail"] == "DUT UNKNOWN-9 not found"
            r = c.get("/api/duts/NORESULT1/certificate.pdf")
            assert r.status_code == 409 and "no stored result" in r.json()["detail"]
            assert httpx.get(f"{url}/api/duts/{serial}/certificate.pdf").status_code == 401
    finally:
        stop_server()


def test_certificate_for_matches_stored_run(store):
    db, _path, written = store
    c = certificate_for(db, written[2]["serial"])
    assert c.run_id == written[2]["run"] and c.station == "line-7" and len(c.fit_points) == 8
    assert render_pdf(c).startswith(b"%PDF")
    assert certificate_for(db, "UNKNOWN") is None


def test_certificate_config_section_optional_and_checked():
    from station.config import parse_config
    from contracts.types import StationError

    base = {"slots": [{"name": "s01", "serial": "/dev/ttyACM0"}], "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1}}
    assert parse_config(base).snapshot()["certificate"] == {"issuer": "", "address": "", "authorised_by": "",
                                                           "reference_thermometer": ""}
    cfg = parse_config({**base, "certificate": {"issuer": "Lab", "authorised_by": "J. Doe"}})
    assert cfg.snapshot()["certificate"]["issuer"] == "Lab"
    with pytest.raises(StationError, match=r"certificate\.signatory: unknown key"):
        parse_config({**base, "certificate": {"signatory": "J. Doe"}})


def test_a_long_measurement_name_wraps_and_stays_with_its_check():
    long_name = "site_specific_measurement_with_a_very_long_name_mg"
    for n_before in range(60, 80):  # wherever it falls, across a page break too
        checks = _many_checks(n_before) + [{"measurement": long_name, "value": 1.0, "outcome": "pass"}]
        cert = build_certificate({"id": 1, "serial": "L1", "verdict_detail": {"checks": checks}}, {"station": "s"}, [])
        pages = layout(cert)
        where = [(n, i) for n, p in enumerate(pages) for i, r in enumerate(p)
                 if r.kind == "table_row" and r.cells[1] and long_name.startswith(r.cells[1]) and r.cells[0] == "PASS"]
        assert len(where) == 1
        n, i = where[0]
        page = pages[n]
        assert page[i].cells[1] + page[i + 1].cells[1] == long_name and page[i + 1].cells[0] == ""
        assert max(len(r.cells[1]) for r in page[i:i + 2]) <= 30
