"""REST and MES for program and verify, over real HTTP on loopback (the daemon on simulated
hardware, SQLite): a stored run's program-and-verify record reaches GET /api/duts/{serial} and the
MES feed GET /api/results; the operator page renders it per slot (app.js is checked by node)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import httpx
import pytest

from web_support import LiveStation, auth, seed_results


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("pv_web"), n_serial=1, n_can=0, speed=100.0) as ls:
        yield ls


def _store_program_verify(db, truth):
    from db.writer import DbWriter
    from contracts.events import DutProgrammed, DutVerified
    from contracts.run_records import ProgramRecord

    (serial, t), (serial2, t2) = list(truth.items())[:2]
    w = DbWriter(db, interval_s=0.05)
    try:
        for ser, tt in ((serial, t), (serial2, t2)):
            w.bind_run(tt["batch_id"], tt["slot"], tt["run_id"])
        w.submit(DutProgrammed(t["batch_id"], slot=t["slot"], serial=serial, program=ProgramRecord.from_json({
            "programmed": True, "crc": "1A2B3C4D", "readback_crc": "1A2B3C4D", "comp": True, "attempts": 2,
            "retries": ["attempt 1: crc_mismatch: ..."]})))
        w.submit(DutVerified(t["batch_id"], slot=t["slot"], serial=serial, verification={
            "passed": True, "flags": [], "e_before_mg": {"x": 40.0, "y": 12.5, "z": 70.0},
            "e_after_mg": {"x": 0.8, "y": 1.1, "z": 2.4}}))
        w.submit(DutProgrammed(t2["batch_id"], slot=t2["slot"], serial=serial2, program=ProgramRecord.from_json({
            "programmed": False, "error_kind": "refused", "error": "CALW refused after 3 attempts", "comp": False})))
        assert w.flush(30)
    finally:
        w.close()
    return serial, serial2


def test_dut_and_mes_results_carry_program_verify(live):
    truth = seed_results(live.station.db, 3, serial_prefix="PV", seed=5)
    ok, refused = _store_program_verify(live.station.db, truth)
    with httpx.Client(base_url=live.url, timeout=30) as c:
        d = c.get(f"/api/duts/{ok}", headers=auth("operator")).json()
        pv = d["program_verify"]
        assert pv["programmed"] and pv["crc"] == "1A2B3C4D" == pv["readback_crc"] and pv["readback_identical"]
        assert pv["comp_on"] and pv["verified"] is True and pv["attempts"] == 2
        assert pv["e_before_mg"] == {"x": 40.0, "y": 12.5, "z": 70.0} and pv["e_after_mg"]["z"] == 2.4
        d2 = c.get(f"/api/duts/{refused}", headers=auth("operator")).json()["program_verify"]
        assert d2["programmed"] is False and d2["error_kind"] == "refused" and d2["verified"] is None
        res = c.get("/api/results", headers=auth("mes"), params={"limit": 100}).json()["results"]
        by_serial = {r["serial"]: r for r in res}
        assert by_serial[ok]["program_verify"]["verified"] is True
        assert by_serial[ok]["program_verify"]["e_after_mg"] == {"x": 0.8, "y": 1.1, "z": 2.4}
        # a verification is data of the run, not a record (design 8): the run's one record is its verdict
        assert sum(1 for r in res if r["serial"] == ok) == 1 and by_serial[ok]["revision"] == 1


@pytest.mark.skipif(shutil.which("node") is None, reason="node not installed")
def test_page_script_parses_and_renders_program_verify():
    js = Path(__file__).resolve().parents[1] / "web" / "static" / "app.js"
    subprocess.run(["node", "--check", str(js)], check=True)
    text = js.read_text() + (js.parent / "i18n" / "en.json").read_text(encoding="utf-8")  # its words: the catalog
    for needle in ("programVerifyTable", "E verified mg", "DutProgrammed", "DutVerified", "compensation "):
        assert needle in text


def test_writer_outbox_carries_program_verify(tmp_path):
    """With the writer's own outbox on, a verification is stored as data (no MES message); the MES
    message is the run's final verdict (design 8), and the feed carries the program-and-verify."""
    from sqlalchemy import select

    from db.models import Outbox
    from db.repository import results_since
    from db.writer import DbWriter
    from contracts.events import DutProgrammed, DutVerdict, DutVerified
    from contracts.run_records import ProgramRecord
    from station.daemon.storage import open_database

    db = open_database(f"sqlite:///{tmp_path / 'o.db'}")
    try:
        bid = db.create_batch("fast-thermal-verified", "t", {})
        run = db.create_run(bid, "s01", "OBX1", "LIS3DSH", {"serial": "OBX1"})
        w = DbWriter(db, interval_s=0.05, outbox=True)
        try:
            w.bind_run(bid, "s01", run)
            w.submit(DutProgrammed(bid, slot="s01", serial="OBX1", program=ProgramRecord.from_json({"programmed": True, "crc": "00000001",
                                                                         "readback_crc": "00000001", "comp": True, "attempts": 1})))
            w.submit(DutVerified(bid, slot="s01", serial="OBX1", verification={
                "passed": False, "flags": ["x: curved residual drift: 9.0 mg"], "e_before_mg": {"x": 30.0, "y": 1.0, "z": 2.0},
                "e_after_mg": {"x": 9.5, "y": float("nan"), "z": 0.4}}))
            assert w.flush(30)
        finally:
            w.close()
        with db.session() as s:
            assert s.scalars(select(Outbox)).all() == []  # program and verify: data, no MES message
        w = DbWriter(db, interval_s=0.05, outbox=True)
        try:
            w.bind_run(bid, "s01", run)
            w.submit(DutVerdict(bid, slot="s01", serial="OBX1", verdict={"verdict": "fail", "grade": "reject"}))
        finally:
            w.close()
        with db.session() as s:
            (p,) = [o.payload for o in s.scalars(select(Outbox)).all()]
        assert p["serial"] == "OBX1" and p["verdict"] == "fail" and p["revision"] == 1
        (item,) = results_since(db, 0)
        assert item["program_verify"]["crc"] == "00000001"
        assert item["program_verify"]["verified"] is False
        assert item["program_verify"]["e_after_mg"] == {"x": 9.5, "y": None, "z": 0.4}  # NaN stored as null
    finally:
        db.dispose()
