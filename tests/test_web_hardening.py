"""Issue 37 (web): the CSV downloads are safe to open in a spreadsheet, and every 4xx a route gives
to schema-valid input is listed in its OpenAPI `responses`.

A live station (web_support.LiveStation: simulated boards, the daemon, SQLite, uvicorn) holds
judged runs whose serials, slots and fault reasons are spreadsheet formulas (`=1+2`, `@SUM(1+1)`,
...); /api/records/spc.csv and /api/records/pareto.csv are fetched over real HTTP and no cell may
start with = + - @, a tab or a CR unless it is a plain number (-51.7 stays a number).
"""

from __future__ import annotations

import csv
import io
import re

import httpx
import pytest

from records_support import segments_for, thermal_result, verdict_of
from web_support import LiveStation, auth

# (a serial holding a CR is left out here: csv.writer(lineterminator="\n") does not quote a bare CR,
# so such a cell would split its row in any reader; safe_cell's leading-CR rule is checked below)
EVIL = ["=1+2", "@SUM(1+1)", "+3+4", "-2+3", "=HYPERLINK(\"http://x\")", "\tTAB", "SAFE-7"]
NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def _write_evil_runs(db) -> list[str]:
    from db import DbWriter
    from contracts.events import DutResult, DutVerdict, SegmentLogged, SlotStateChanged
    from contracts.run_records import ThermalReport

    w = DbWriter(db, interval_s=0.02)
    batch = db.create_batch("fast-thermal", "mallory", {"name": db.station}, state="running")
    for i, serial in enumerate(EVIL):
        slot = f"s{i + 1:02d}"
        run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial, "sensor": "LIS3DSH"})
        w.bind_run(batch, slot, run)
        tdb = (-0.517 - 0.01 * i, 0.2, 0.1)  # negative values: they must stay numbers in the CSV
        tdsf = (-51.7, -120.0, 30.0)
        for sg in segments_for(tdb, tdsf):
            w.submit(SegmentLogged(batch, slot, serial, 0, sg))
        v = verdict_of(tdb, tdsf)
        if i % 2:  # an error whose reason is a formula: a Pareto cause
            v = {**v, "verdict": "error", "reason": f"=cmd|' /C calc'!A{i}", "reasons": [f"=cmd|' /C calc'!A{i}"]}
        w.submit(DutResult(batch, slot, serial, thermal=ThermalReport.from_json(thermal_result(tdb, tdsf))))
        w.submit(SlotStateChanged(batch, slot, serial, "done"))
        w.submit(DutVerdict(batch, slot, serial, verdict=v))
    w.flush()
    db.set_batch_state(batch, "finished")
    w.close()
    return EVIL


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("hardening"), n_serial=1, n_can=1, speed=400.0) as ls:
        _write_evil_runs(ls.station.db)
        yield ls


def _unsafe(cells: list[str]) -> list[str]:
    return [c for c in cells if c[:1] in ("=", "+", "-", "@", "\t", "\r") and not NUMBER.fullmatch(c)]


def test_csv_cells_are_never_formulas_but_negative_numbers_stay_numbers(live):
    h = auth("mes")
    r = httpx.get(f"{live.url}/api/records/spc.csv", params={"parameter": "tdsf_ppm_per_c:x"}, headers=h, timeout=30)
    assert r.status_code == 200, r.text
    rows = list(csv.reader(io.StringIO(r.text)))
    cells = [c for row in rows for c in row]
    assert _unsafe(cells) == [], _unsafe(cells)
    body = {row[5]: row for row in rows[1:]}  # serial column
    for serial in EVIL:
        want = serial if serial == "SAFE-7" else "'" + serial
        assert want in body, (want, sorted(body))
        assert body[want][7] == "-51.7"  # the value: a plain negative number, untouched
    assert float(body["SAFE-7"][7]) == -51.7
    r = httpx.get(f"{live.url}/api/records/pareto.csv", headers=h, timeout=30)
    assert r.status_code == 200, r.text
    cells = [c for row in csv.reader(io.StringIO(r.text)) for c in row]
    assert _unsafe(cells) == [], _unsafe(cells)
    assert any(c.startswith("'=cmd|") for c in cells), cells  # the cause is there, as text
    from station.records.csv_cells import safe_cell

    assert [safe_cell(x) for x in ("-51.7", "+3", "1e-5", "-.5", "-", "-1-1", "@x", "a=b", "\rX", 7, -2.5)] == \
        ["-51.7", "+3", "1e-5", "-.5", "'-", "'-1-1", "'@x", "a=b", "'\rX", 7, -2.5]


# Schema-valid input the station answers 4xx (dates the pattern lets through that are no calendar
# day, a profile or slot the configuration does not have): each status must be in the document.
CASES = [
    ("get", "/api/records/spc", {"params": {"from": "0000-00-00"}}),
    ("get", "/api/spc", {"params": {"from": "0000-00-00"}}),
    ("get", "/api/records/spc.csv", {"params": {"from": "0000-00-00"}}),
    ("get", "/api/spc.csv", {"params": {"from": "0000-00-00"}}),
    ("get", "/api/records/pareto", {"params": {"from": "0000-00-00"}}),
    ("get", "/api/records/pareto.csv", {"params": {"to": "2026-02-30"}}),
    ("post", "/api/batches", {"json": {"profile": "0", "slots": ["0"], "operator": "0"}}),
    ("get", "/api/results", {"params": {"since": "0000-00-00"}}),
]


def test_every_4xx_answered_to_schema_valid_input_is_listed_in_the_openapi(live):
    doc = live.app.openapi()
    ops = {(m, p): op for p, item in doc["paths"].items() for m, op in item.items()}
    seen = []
    with httpx.Client(base_url=live.url, headers=auth("admin"), timeout=30) as c:
        for method, path, kw in CASES:
            op = ops[(method, path)]
            r = c.request(method.upper(), path, **kw)
            assert 400 <= r.status_code < 500, (path, r.status_code, r.text)
            assert str(r.status_code) in op["responses"], (method, path, r.status_code, sorted(op["responses"]))
            assert r.json()["detail"], r.text
            seen.append((method.upper(), path, r.status_code))
    assert len(seen) == len(CASES) == 8
    # and the words: those 422s say that schema-valid input can get them
    for method, path, _kw in CASES:
        assert "schema-valid" in ops[(method, path)]["responses"]["422"]["description"], path
