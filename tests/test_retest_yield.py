"""Retests and yields over real HTTP: runs judged by station/decisions/verdicts.py are written through the real
DbWriter into the SQLite file of a live station (Station + web app on 127.0.0.1), then read back
through GET /api/yield, /api/results, /api/duts/{serial} and /api/duts/{serial}/runs.

    R1: fail, then pass on the retest        first pass no,  final pass yes
    R2: pass                                 first pass yes, final pass yes
    R3: error (faulted), then marginal       first pass no,  final pass no (marginal is not pass)
    R4: pass, then an aborted retest (error) first pass yes, final pass yes: the latest VALID attempt
                                             (attempt 1) stays the DUT's result
"""

from __future__ import annotations

import httpx
import pytest

from contracts.events import DutResult, DutVerdict, SlotStateChanged
from contracts.run_records import ThermalReport
from station.decisions.limits import Limit, ProductSpec
from station.decisions.verdicts import Measurement, decide
from web_support import LiveStation, auth

SPEC = ProductSpec(name="yield-limits", version="9", sensor="LIS3DSH",
                   limits=[Limit(measurement="tdsf_ppm_per_c", low=-500, unit="ppm/C", label="TDSF", required=True)])
PLAN = {"R1": ["fail", "pass"], "R2": ["pass"], "R3": ["error", "marginal"], "R4": ["pass", "error"]}
TDSF = {"pass": -200.0, "fail": -612.0, "marginal": -497.0}


def verdict(kind: str) -> dict:
    if kind == "error":
        return decide([], SPEC, state="faulted", fault_reason="faulted: link lost").to_json()
    ms = [Measurement("tdsf_ppm_per_c", TDSF[kind], "ppm/C", ax, 2.0) for ax in "xyz"]
    return decide(ms, SPEC).to_json()


def seed(db) -> dict[str, list[int]]:
    from db.writer import DbWriter

    runs: dict[str, list[int]] = {s: [] for s in PLAN}
    writer = DbWriter(db, interval_s=0.05)
    try:
        for attempt in range(2):
            batch = db.create_batch("fast-thermal", "pytest", {})
            for k, (serial, kinds) in enumerate(PLAN.items()):
                if attempt >= len(kinds):
                    continue
                slot = f"s{k + 1}"
                run_id = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial})
                writer.bind_run(batch, slot, run_id)
                v = verdict(kinds[attempt])
                v.update(attempt=db.run_attempt(run_id), run_id=run_id)  # as station/decisions/moment.py does
                if kinds[attempt] == "error":
                    writer.submit(SlotStateChanged(batch, slot=slot, serial=serial, state="faulted", fault_reason="link lost"))
                    writer.submit(DutVerdict(batch, slot=slot, serial=serial, verdict=v))
                else:
                    axes = {ax: {"tdb_mg_per_c": 0.1, "tdsf_ppm_per_c": TDSF[kinds[attempt]]} for ax in "xyz"}
                    writer.submit(DutResult(batch, slot=slot, serial=serial, thermal=ThermalReport.from_json({"axes": axes})))
                    writer.submit(SlotStateChanged(batch, slot=slot, serial=serial, state="done"))
                    writer.submit(DutVerdict(batch, slot=slot, serial=serial, verdict=v))  # final: the MES record
                runs[serial].append(run_id)
            assert writer.flush(30)
            db.set_batch_state(batch, "finished")
    finally:
        writer.close()
    return runs


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("yield"), n_serial=1, n_can=0, speed=100.0) as ls:
        ls.runs = seed(ls.station.db)
        yield ls


def test_attempts_are_numbered_per_serial(live):
    with httpx.Client(base_url=live.url, timeout=10) as c:
        for serial, kinds in PLAN.items():
            runs = c.get(f"/api/duts/{serial}/runs", headers=auth("operator")).json()
            assert [(r["attempt"], r["verdict"]) for r in runs] == list(reversed(list(enumerate(kinds, start=1))))
            assert all(r["limits_name"] == "yield-limits" and r["limits_version"] == "9" for r in runs)
        run = c.get(f"/api/runs/{live.runs['R1'][0]}", headers=auth("operator")).json()
        checks = run["verdict_detail"]["checks"]
        assert {(ch["axis"], ch["outcome"], ch["value"], ch["low"]) for ch in checks} == {
            (ax, "fail", -612.0, -500.0) for ax in "xyz"}


def test_latest_valid_attempt_is_the_duts_result(live):
    with httpx.Client(base_url=live.url, timeout=10) as c:
        expect = {"R1": (2, "pass"), "R2": (1, "pass"), "R3": (2, "marginal"), "R4": (1, "pass")}
        for serial, (attempt, v) in expect.items():
            d = c.get(f"/api/duts/{serial}", headers=auth("operator")).json()
            assert (d["attempt"], d["verdict"]) == (attempt, v), serial
        assert c.get("/api/duts/R1", headers=auth("operator")).json()["reason"] == "all limits met"
        r3 = c.get("/api/duts/R3", headers=auth("operator")).json()
        assert r3["grade"] == "hold" and "crosses limit -500" in r3["reason"]


def test_first_pass_and_final_yield(live):
    with httpx.Client(base_url=live.url, timeout=10) as c:
        y = c.get("/api/yield", headers=auth("mes")).json()
        assert (y["duts"], y["attempts"], y["retested"], y["first_pass"], y["final_pass"]) == (4, 7, 3, 2, 3)
        assert y["first_pass_yield"] == pytest.approx(0.5) and y["final_yield"] == pytest.approx(0.75)
        assert c.get("/api/yield", headers=auth("operator")).status_code in (200, 403)


def test_mes_feed_carries_every_attempt_with_its_verdict(live):
    with httpx.Client(base_url=live.url, timeout=10) as c:
        page = c.get("/api/results", headers=auth("mes")).json()
        got = [(r["serial"], r["attempt"], r["verdict"], r["grade"], r["limits_version"]) for r in page["results"]]
        assert ("R1", 1, "fail", "reject", "9") in got and ("R1", 2, "pass", "A", "9") in got
        assert ("R3", 1, "error", "retest", "9") in got and ("R4", 2, "error", "retest", "9") in got
        assert len(got) == 7
        fail = next(r for r in page["results"] if r["serial"] == "R1" and r["attempt"] == 1)
        assert fail["reason"].startswith("x TDSF -612 ppm/C, limit -500")


def test_openapi_documents_the_decision_and_the_webhook(live):
    with httpx.Client(base_url=live.url, timeout=10) as c:
        doc = c.get("/openapi.json").json()
    schemas = doc["components"]["schemas"]
    for name in ("ResultOut", "SlotStatus", "DutOut", "MesResultPayload"):
        assert {"verdict", "grade", "attempt", "limits_version", "reason"} <= set(schemas[name]["properties"]), name
    assert {"decision", "sorting", "time_left"} <= set(schemas["BatchStatus"]["properties"])
    assert "/api/yield" in doc["paths"]
    hook = doc["webhooks"]["mes-result"]["post"]
    assert hook["requestBody"]["content"]["application/json"]["schema"]["$ref"].endswith("/MesResultPayload")
