"""Calibration certificate (issue 13): the pure core from stored rows, the PDF through the CLI and
REST, read back with poppler (pdftotext for the words, pdftoppm renders it to a PNG in artifacts/)."""

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
from station.certificate import build_certificate, certificate_for, render_pdf
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


@poppler
def test_cli_writes_certificate_pdf_with_serial_verdict_coefficients(store, tmp_path):
    db, path, written = store
    w = written[0]
    out = tmp_path / "cert.pdf"
    r = subprocess.run([sys.executable, "-m", "station.cli", "certificate", w["serial"], "--db", str(path), "--out", str(out)],
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
    r = subprocess.run([sys.executable, "-m", "station.cli", "certificate", "NOPE", "--db", str(path)],
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
