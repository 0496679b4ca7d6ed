"""Records filters, SPC groups and the failure Pareto (issue 24) on a real SQLite database holding a
line's month (tests/records_support.py spc_line_lots: two products, two limits versions of one,
three work orders, two stations, three days): db.repository.judged_runs's filters against the runs
written, then the REST answers over real HTTP: one chart per group and never a mix, each point
judged by its own limits, the CSV equal to the JSON the page draws, 422 on a bad date."""

from __future__ import annotations

import csv
import io
from datetime import datetime, timezone
from types import SimpleNamespace

import httpx
import pytest

from db import Database
from db import repository as R
from records_support import spc_line_lots, write_spc_line
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

TOKEN = "mes-token-filters-01"
H = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    path = tmp_path_factory.mktemp("filters") / "r.db"
    db = Database(f"sqlite:///{path}", station="line-2")
    db.upgrade()
    db9 = Database(f"sqlite:///{path}", station="line-9")
    written = write_spc_line(db, db9)
    app = create_app(SimpleNamespace(config=None, bus=None, db=db), repo=DbRepository(db),
                     tokens=TokenStore([(TOKEN, "mes", "mes")]), outbox=False)
    url, stop = serve_in_thread(app)
    yield db, url, written
    stop()
    db.dispose()
    db9.dispose()


def _ids(written, *lots):
    return [w["run"] for w in written if w["lot"] in lots]


def _utc(day: str) -> datetime:
    return datetime.fromisoformat(day).replace(tzinfo=timezone.utc)


def test_judged_runs_filters_select_exactly_the_runs_written(line):
    db, _url, written = line
    ids = lambda **kw: [r["run_id"] for r in R.judged_runs(db, **kw)]  # noqa: E731
    assert ids() == [w["run"] for w in sorted(written, key=lambda w: w["judged_at"])]  # oldest first
    assert ids(judged_from=_utc("2026-11-19"), judged_to=_utc("2026-11-20")) == _ids(written, 1)
    assert ids(part_number="ACC-100") == _ids(written, 0, 1)
    assert ids(part_number="ACC-200", part_revision="B") == _ids(written, 2)
    assert ids(part_number="ACC-200", part_revision="A") == []
    assert ids(part_number="") == _ids(written, 3)  # '' is a value: the batch carried no part number
    assert ids(work_order="WO-2") == _ids(written, 1)
    assert ids(limits_name="LIS3DSH", limits_version="1") == sorted(_ids(written, 0, 3), key=lambda i: next(
        w["judged_at"] for w in written if w["run"] == i))
    assert ids(station="line-9") == _ids(written, 3)
    # the limit applies after the filters: the newest 5 of ACC-100 are B's last 5, not C's or D's
    assert ids(limit=5, part_number="ACC-100") == _ids(written, 1)[-5:]
    run = R.judged_runs(db, work_order="WO-1")[0]
    assert (run["product"], run["part_number"], run["part_revision"], run["lot"], run["state"]) == \
        ("ACC-100 rev A", "ACC-100", "A", "", "done")
    facets = {(f["station"], f["product"], f["work_order"], f["limits_version"]): f["runs"] for f in R.judged_facets(db)}
    lots = spc_line_lots()
    assert facets == {("line-2", "ACC-100 rev A", "WO-1", "1"): len(lots[0].tdb_x) + 3,
                      ("line-2", "ACC-100 rev A", "WO-2", "2"): len(lots[1].tdb_x),
                      ("line-2", "ACC-200 rev B", "WO-3", "1"): len(lots[2].tdb_x),
                      ("line-9", "", "", "1"): len(lots[3].tdb_x)}


def _points(written, lot):
    return [(w["run"], w["tdb"][0]) for w in written if w["lot"] == lot and w["tdb"] is not None]


def test_spc_answers_one_group_at_a_time_each_point_by_its_own_limits(line):
    _db, url, written = line
    body = httpx.get(f"{url}/api/records/spc", headers=H, timeout=30).json()
    labels = [g["label"] for g in body["groups"]]
    assert labels == ["ACC-200 rev B · ADXL355 v1", "unspecified product · LIS3DSH v1",
                      "ACC-100 rev A · LIS3DSH v2", "ACC-100 rev A · LIS3DSH v1"]  # newest run first
    assert body["group"]["label"] == labels[0] and body["label"] == "TDB x (mg/°C)"
    lot_of = {"ACC-200 rev B · ADXL355 v1": 2, "unspecified product · LIS3DSH v1": 3,
              "ACC-100 rev A · LIS3DSH v2": 1, "ACC-100 rev A · LIS3DSH v1": 0}
    for g in body["groups"]:
        b = httpx.get(f"{url}/api/records/spc", params={"group": g["key"], "parameter": "tdb_mg_per_c:x"}, headers=H,
                      timeout=30).json()
        pts = [(p["run_id"], p["value"]) for p in b["points"]]
        assert pts == _points(written, lot_of[g["label"]]), g["label"]  # this group's runs, all of them, only them
        assert [p["index"] for p in b["points"]] == list(range(1, len(pts) + 1))
        lim = spc_line_lots()[lot_of[g["label"]]].tdb_limit
        assert {(p["low"], p["high"]) for p in b["points"]} == {(-lim, lim)}
        assert b["capability"]["out_of_spec"] == sum(abs(v) > lim for _r, v in pts)
    # B (v2, USL 1.0): its two 1.1 are out of ITS spec; A (v1, USL 1.5): its 1.2s are not, its 1.6 is
    b2 = httpx.get(f"{url}/api/records/spc", params={"group": body["groups"][2]["key"]}, headers=H, timeout=30).json()
    assert [p["spec"] for p in b2["points"] if p["value"] == 1.1] == ["above USL", "above USL"]
    assert b2["capability"]["cpk"] is None and b2["capability"]["reason"] == "n=12 < 25"
    b1 = httpx.get(f"{url}/api/records/spc", params={"group": body["groups"][3]["key"]}, headers=H, timeout=30).json()
    assert {p["value"]: p["spec"] for p in b1["points"] if p["value"] > 1.0} == {1.2: "in spec", 1.6: "above USL"}
    shifted = [p for p in b1["points"] if any(f["rule"] == "2" for f in p["flags"])]
    assert shifted and all("9 in a row on one side" in next(f["name"] for f in p["flags"] if f["rule"] == "2")
                           for p in shifted)
    c = body["capability"]
    assert c["n"] == 28 and c["cpk"] < 1.33 and c["below_target"] is True and c["cpk_ci_low"] < c["cpk"] < c["cpk_ci_high"]
    assert body["rules"]["7"] == "15 in a row within 1 sigma" and body["parameter_labels"]["tdsf_ppm_per_c:z"] == \
        "TDSF z (ppm/°C)"


def test_filters_over_http_and_the_csv_is_the_table_shown(line):
    _db, url, written = line
    get = lambda path, **q: httpx.get(f"{url}{path}", params=q, headers=H, timeout=30)  # noqa: E731
    assert [g["label"] for g in get("/api/records/spc", work_order="WO-2").json()["groups"]] == \
        ["ACC-100 rev A · LIS3DSH v2"]
    assert [g["label"] for g in get("/api/records/spc", station="line-9").json()["groups"]] == \
        ["unspecified product · LIS3DSH v1"]
    assert [g["label"] for g in get("/api/records/spc", product="(unspecified)").json()["groups"]] == \
        ["unspecified product · LIS3DSH v1"]
    assert [g["label"] for g in get("/api/records/spc", product="ACC-100 rev A").json()["groups"]] == \
        ["ACC-100 rev A · LIS3DSH v2", "ACC-100 rev A · LIS3DSH v1"]
    day = get("/api/records/spc", **{"from": "2026-11-19", "to": "2026-11-19"}).json()
    assert [g["label"] for g in day["groups"]] == ["ACC-100 rev A · LIS3DSH v2"] and day["filters"]["from"] == "2026-11-19"
    opts = day["options"]  # the selects: the date range's choices, not narrowed by the other filters
    assert [o["value"] for o in opts["products"]] == ["ACC-100 rev A"] and opts["work_orders"][0]["value"] == "WO-2"
    everything = get("/api/records/spc", product="ACC-100 rev A").json()["options"]
    assert [o["value"] for o in everything["products"]] == ["(unspecified)", "ACC-100 rev A", "ACC-200 rev B"]
    # a bad date: 422 naming the field; an empty range: 422 saying why
    r = get("/api/records/spc", **{"from": "2026-11-31"})
    assert r.status_code == 422 and "from" in r.json()["detail"]
    r = get("/api/records/pareto.csv", **{"from": "2026-11-20", "to": "2026-11-18"})
    assert r.status_code == 422 and r.json()["detail"] == "from 2026-11-20 is after to 2026-11-18"
    assert get("/api/records/spc", group="nope").status_code == 404
    # the CSV of what is shown: the same query gives the table's columns and rows
    q = {"product": "ACC-100 rev A", "group": get("/api/records/spc", work_order="WO-1").json()["group"]["key"]}
    shown = get("/api/records/spc", **q).json()
    rows = list(csv.reader(io.StringIO(get("/api/records/spc.csv", **q).text)))
    assert rows[0] == shown["columns"] and len(rows) - 1 == len(shown["points"]) == len(_points(written, 0))
    for row, p in zip(rows[1:], shown["points"]):
        assert [int(row[0]), int(row[1]), row[5], row[6], float(row[7]), float(row[9]), row[10], row[12]] == \
            [p["index"], p["run_id"], p["serial"], p["at"], p["value"], p["high"], p["spec"],
             "; ".join(f"{f['rule']}: {f['name']}" for f in p["flags"])]
    # the Pareto and its CSV, under a filter
    par = get("/api/records/pareto", work_order="WO-1").json()
    assert (par["runs"], par["runs_error"]) == (len(_ids(written, 0)), 3)
    # one cause per failed or error run, by name (station/records/causes.py), never "faulted"
    assert [(e["what"], e["fail"], e["error"]) for e in par["causes"]] == [
        ("limit: TDB", 1, 0), ("link lost", 0, 1), ("no samples", 0, 1), ("not measured", 0, 1)]
    assert [(c["what"], c["fail"], c["error"]) for c in par["checks"]] == [("TDB x", 1, 0), ("TDB y", 0, 1)]
    prow = list(csv.reader(io.StringIO(get("/api/records/pareto.csv", work_order="WO-1").text)))
    assert prow[0] == par["columns"] and prow[1:] == [
        [r["table"], str(r["rank"]), r["what"], str(r["fail"]), str(r["error"]), str(r["count"]), f"{r['pct']:.1f}",
         f"{r['cum_pct']:.1f}"] for r in par["checks"] + par["causes"]]
    assert get("/api/records/pareto", station="line-9").json()["checks"] == []  # D: all passed
    assert httpx.get(f"{url}/api/records/pareto", timeout=30).status_code == 401
