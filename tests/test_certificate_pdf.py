"""The calibration certificate of a verified run lists EVERY check of its verdict (issue 22).

A program-and-verify run is judged by the real judging code (station/decisions/verdicts.final_verdict against
the built-in LIS3DSH limits from a real station config) and stored through the real DbWriter in a
SQLite file. Its verdict has ~30 checks and fails on the verified drift error E_FS of axis z, a
check the old certificate (the first 14 checks only) never showed. The PDF is read back with
poppler's pdftotext: every check is a row, the failing one on page 1, "page x of N" on every page,
the k = 2 expanded uncertainty, the decision rule, traceability, the model equation and the
configured issuer. The certificate id is stable for one record and changes with a superseding one.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from db import Database, DbWriter
from records_support import segments_for
from station.records.certificate import certificate_for
from station.records.certificate_layout import layout
from station.records.certificate_pdf import render_pdf
from station.config import parse_config
from contracts.events import DutProgrammed, DutResult, DutVerdict, DutVerified, SegmentLogged, SlotStateChanged
from contracts.run_records import ProgramRecord, ThermalReport
from station.decisions.verdicts import RunRecord, final_verdict

ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = ROOT / "artifacts"
SERIAL = "VER-0042"
ISSUER = "Acme Sensors GmbH, calibration laboratory"
ADDRESS = "Werkstrasse 5, 70565 Stuttgart, Germany"
AUTHORISED = "Dr. Jana Novak, head of calibration"
THERMOMETER = "Pt100 SN 4711, certificate 2026-0815, due 2027-02"
EQUATION = "Acc(T) = Acc0 · (1 + TDSF · (T - Tref)) + TDB · (T - Tref)"

pytestmark = pytest.mark.skipif(
    shutil.which("pdftotext") is None,
    reason="poppler-utils (pdftotext) not installed: the certificate PDF cannot be read back "
           "(scripts/test.sh installs it)")

CONFIG = {
    "name": "line-9",
    "slots": [{"name": "s01", "serial": "/dev/ttyACM0"}],
    "lamp": {"tcp": {"host": "127.0.0.1", "port": 5020}, "unit": 1},
    "thermometer": {"rtu": {"port": "/dev/ttyUSB0"}, "unit": 2},
    "certificate": {"issuer": ISSUER, "address": ADDRESS, "authorised_by": AUTHORISED,
                    "reference_thermometer": THERMOMETER},
}
TDB = (1.46, 0.31, -0.42)  # x: 1.46 +- 2 x 0.0101 reaches into the 0.05 marginal band below the 1.5 limit
TDSF = (-120.0, -210.0, 0.0)  # z: positive, clamped to 0
E_BEFORE_MG = {"x": 60.0, "y": 40.0, "z": 200.0}
E_AFTER_MG = {"x": 3.0, "y": 2.5, "z": 32.0}  # z: within 25 % of E before (axis rule passes) but 1.6 %FS


def thermal_result() -> dict:
    """A thermal result in the daemon's shape (thermal_calibration.calibrate): offline axes, the
    streaming result, and the residual report the verdict judges drift, bow, ramp and noise from."""
    axes = {ax: {"tdb_mg_per_c": b, "tdsf_ppm_per_c": s, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": 4.0,
                 "tdsf_clamped": ax == "z"} for ax, b, s in zip("xyz", TDB, TDSF)}
    streaming = {ax: {**a, "tdb_mg_per_c": a["tdb_mg_per_c"] + 0.02, "tdsf_ppm_per_c": a["tdsf_ppm_per_c"] - 6.0}
                 for ax, a in axes.items()}
    residual = {ax: {"drift_error_fs_pct": 0.4, "drift_error_fs_sigma_pct": 0.05, "drift_error_mg": 8.0,
                     "drift_error_sigma_mg": 1.0, "bow_mg": 0.8, "bow_sigma_mg": 0.3, "ramp_residual_rms_mg": 0.5,
                     "noise_ug_per_sqrt_hz": 420.0} for ax in "xyz"}
    return {"serial": SERIAL, "sensor": "LIS3DSH", "axes": axes,
            "offline": {"method": "offline", "n_segments": 8, "axes": axes},
            "streaming": {"method": "streaming", "n_segments": 8, "axes": streaming},
            "residual": {"axes": residual}}


PROGRAM = {"programmed": True, "crc": "1A2B3C4D", "readback_crc": "1A2B3C4D", "comp": True, "attempts": 1}
VERIFICATION = {
    "passed": True, "flags": [], "rise_c": 16.0, "temp_from_c": 26.0, "temp_to_c": 42.0, "range_c": [-10.0, 60.0],
    "e_before_mg": E_BEFORE_MG, "e_after_mg": E_AFTER_MG,
    "e_after_sigma_mg": {"x": 1.0, "y": 1.0, "z": 1.5},
    "e_after_fs_pct": {ax: v / 2000.0 * 100.0 for ax, v in E_AFTER_MG.items()},
    "e_after_fs_sigma_pct": {"x": 0.05, "y": 0.05, "z": 0.075},
    "axes": {ax: {"passed": True} for ax in "xyz"},
}


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """A verified run judged by final_verdict and stored in a SQLite file; (db, path, verdict)."""
    cfg = parse_config(CONFIG)
    spec = cfg.product_for("LIS3DSH")
    record = RunRecord(analysis="thermal", program_verify=True, end_state="done", result=thermal_result(),
                       link_stats={"samples_lost": 2, "frames_bad_checksum": 1}, n_samples=20_000,
                       program=PROGRAM, verification=VERIFICATION)
    verdict = final_verdict(record, spec)
    path = tmp_path_factory.mktemp("cert_pdf") / "station.db"
    db = Database(f"sqlite:///{path}", station=cfg.name)
    db.upgrade()
    batch = db.create_batch("fast-thermal-verified", "alice", cfg.snapshot(), state="running")
    run = db.create_run(batch, "s01", SERIAL, "LIS3DSH", {"serial": SERIAL, "sensor": "LIS3DSH", "fw": "3.1.4"})
    w = DbWriter(db, interval_s=0.02)
    try:
        w.bind_run(batch, "s01", run)
        for sg in segments_for(TDB, TDSF, temps=(24.5, 31.0, 38.0, 45.5)):
            w.submit(SegmentLogged(batch, "s01", SERIAL, 0, sg))
        w.submit(DutResult(batch, "s01", SERIAL, thermal=ThermalReport.from_json(thermal_result())))
        w.submit(DutProgrammed(batch, slot="s01", serial=SERIAL, program=ProgramRecord.from_json(PROGRAM)))
        w.submit(DutVerified(batch, slot="s01", serial=SERIAL, verification=VERIFICATION))
        w.submit(SlotStateChanged(batch, "s01", SERIAL, "done"))
        w.submit(DutVerdict(batch, "s01", SERIAL, verdict={**verdict.to_json(), "attempt": 1, "run_id": run}))
        assert w.flush(30)
    finally:
        w.close()
    db.set_batch_state(batch, "finished")
    yield db, path, verdict, (batch, run)
    db.dispose()


def pdf_text(pdf: Path, page: int | None = None) -> str:
    pages = ["-f", str(page), "-l", str(page)] if page else []
    return subprocess.run(["pdftotext", "-layout", *pages, str(pdf), "-"], capture_output=True, text=True,
                          check=True).stdout


CHECK_ROW = re.compile(r"^\s*(PASS|MARGINAL|FAIL|ERROR)\s+([a-z_]+)\s+([xyz-])\s", re.M)


def test_verdict_has_a_failing_check_beyond_the_first_14(stored):
    """The scenario itself: a verified profile's ~30 checks, failing on a late one."""
    _db, _path, verdict, _ids = stored
    assert verdict.verdict == "fail", verdict.reasons
    failing = [(c.measurement, c.axis) for c in verdict.checks if c.outcome == "fail"]
    assert failing == [("verified_drift_error_fs_pct", "z")]
    assert min(i for i, c in enumerate(verdict.checks) if c.outcome == "fail") >= 14
    assert len(verdict.checks) >= 28
    assert [(c.measurement, c.axis) for c in verdict.checks if c.outcome == "marginal"] == [("tdb_mg_per_c", "x")]


def test_pdf_lists_every_check_worst_first_over_numbered_pages(stored, tmp_path):
    db, _path, verdict, (_batch, run) = stored
    cert = certificate_for(db, SERIAL)
    pdf = tmp_path / "cert.pdf"
    pdf.write_bytes(render_pdf(cert))
    text = pdf_text(pdf)
    n_pages = len(layout(cert))
    assert n_pages >= 2
    # every page says which page of how many, and the PDF has exactly that many
    for k in range(1, n_pages + 1):
        assert f"page {k} of {n_pages}" in text
    assert f"page {n_pages + 1} of" not in text and text.count("\f") == n_pages

    # every check of the verdict is a row (measurement and axis), no more, no less
    rows = CHECK_ROW.findall(text)
    assert Counter((m, ax) for _o, m, ax in rows) == Counter((c.measurement, c.axis or "-") for c in verdict.checks)
    for c in verdict.checks:
        assert c.measurement in text
    outcomes = [o for o, _m, _ax in rows]
    assert outcomes == sorted(outcomes, key=["FAIL", "MARGINAL", "PASS"].index)  # worst first

    # the failing check is on page 1, with its value, unit, limit, sigma
    page1 = pdf_text(pdf, 1)
    fail_rows = [line for line in page1.splitlines() if re.match(r"\s*FAIL\s+verified_drift_error_fs_pct\s+z\s", line)]
    assert len(fail_rows) == 1, page1
    # value 1.6 %FS, limit <= 1, 1-sigma 0.075 (as stored), guard half-width 2 x 0.075
    assert re.search(r"z\s+1\.6\s+%FS\s+≤\s*1\s+0\.075\s+0\.15\s*$", fail_rows[0]), fail_rows[0]
    assert "Verdict FAIL" in page1 and "page 1 of" in page1

    # ISO/IEC 17025 7.8 items; a paragraph may run over a page break: the running footer and header
    # between its halves are left out of the flat text (each is checked above)
    body = [ln for ln in text.replace("\f", "\n").splitlines()
            if not re.match(r"\s*Certificate line-9-run\d+-rev1\s+page \d+ of \d+\s*$", ln)
            and not re.match(r"\s*Calibration certificate line-9-run\d+-rev1 · serial \S+\s+" + re.escape(ISSUER) + r"\s*$", ln)]
    flat = " ".join(" ".join(body).split())
    assert f"Certificate line-9-run{run}-rev1" in flat
    assert ISSUER in flat and ADDRESS in flat and f"Authorised by: {AUTHORISED}" in flat
    assert "U = k · u with coverage factor k = 2" in flat and "approximately 95 %" in flat
    u_tdb_x = math.hypot(0.01, 1.5e-3)  # the measured sigma and the limits set's u_sys (spec_limits)
    assert f"TDB x {TDB[0]:+.4g} ± {2 * u_tdb_x:.2g} mg/°C {u_tdb_x:.2g}" in flat
    assert "clamped to 0 (not observable)" in flat
    assert "Guarded acceptance" in flat and "k = 2 (the limits set's guard_sigma)" in flat
    assert "σ = sqrt(σ_measured² + u_sys²)" in flat and "MARGINAL: an interval crosses a limit" in flat
    assert "Traceability" in flat and "NOT metrologically traceable to the SI kelvin" in flat
    assert "modbus rtu /dev/ttyUSB0 unit 2" in flat and THERMOMETER in flat
    assert "the reference is gravity" in flat
    assert EQUATION in text and "Tref = 25 °C" in flat and "TDB: thermal drift of the bias in mg/°C" in flat
    assert "TDSF: thermal drift of the scale factor in ppm/°C" in flat
    assert "LIS3DSH-default version 2" in flat and "thermal-cal-station 0.1.0" in flat
    assert "board sensor) over the 8 stored stable segments: 24.5 to 45.5 °C" in flat
    assert "Verification heat (program and verify): 26.0 to 42.0 °C" in flat
    assert "Ambient (room) temperature and humidity: not recorded" in flat
    # the verified figures, with units
    assert "CRC-32 written 1A2B3C4D, read back 1A2B3C4D: CRC readback match yes" in flat
    assert "E before (mg)" in flat and "E_FS after (%FS) ± U, k=2" in flat
    assert "z 200 32 ± 3 10 1.6 ± 0.15 passed" in flat

    ARTIFACTS.mkdir(exist_ok=True)
    if shutil.which("pdftoppm"):
        subprocess.run(["pdftoppm", "-png", "-r", "60", "-f", "1", "-l", "1", "-singlefile", str(pdf),
                        str(ARTIFACTS / "certificate-verified-p1")], check=True)


def test_certificate_id_stable_per_record_new_for_a_superseding_one(stored):
    db, _path, verdict, (batch, run) = stored
    first = certificate_for(db, SERIAL).certificate_id
    assert certificate_for(db, SERIAL).certificate_id == first == f"line-9-run{run}-rev1"
    w = DbWriter(db, interval_s=0.02)  # the run judged again (a resumed batch): a new record, revision 2
    try:
        w.bind_run(batch, "s01", run)
        w.submit(DutVerdict(batch, "s01", SERIAL, verdict={**verdict.to_json(), "attempt": 1, "run_id": run}))
        assert w.flush(30)
    finally:
        w.close()
    assert certificate_for(db, SERIAL).certificate_id == f"line-9-run{run}-rev2"


def test_cli_config_supplies_the_issuer_and_missing_issuer_says_not_configured(stored, tmp_path):
    db, path, _verdict, _ids = stored
    toml = tmp_path / "other.toml"
    toml.write_text('[[slots]]\nname = "s01"\nserial = "/dev/ttyACM0"\n[lamp]\ntcp = { host = "127.0.0.1" }\n'
                    'unit = 1\n[certificate]\nissuer = "Other Lab Ltd"\n')
    out = tmp_path / "c.pdf"
    r = subprocess.run([sys.executable, "-m", "cli", "certificate", SERIAL, "--db", str(path),
                        "--config", str(toml), "--out", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    flat = " ".join(pdf_text(out).split())
    assert "Issued by Other Lab Ltd" in flat and ISSUER not in flat
    assert "Authorised by: not configured" in flat and "Address / place not configured" in flat
