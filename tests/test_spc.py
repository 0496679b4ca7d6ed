"""Yield and SPC (issue 13): the pure core against hand-computed I-MR limits and Cpk, and the REST
answers (/api/spc, /api/spc.csv) over real HTTP on a database holding several judged batches."""

from __future__ import annotations

import csv
import io
import math
from types import SimpleNamespace

import httpx
import numpy as np
import pytest

from db import Database
from records_support import LIMITS, write_batches
from station.records import spc
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

TOKEN = "mes-token-spc-0001"


def _run(i, value, slot="s01", batch=1, verdict="pass", at="2026-11-20T10:00:00+00:00", low=-1.0, high=5.0):
    return {"run_id": i, "batch_id": batch, "station": "A", "slot": slot, "serial": f"S{i}", "judged_at": at,
            "verdict": verdict, "limits_name": "LIS3DSH",
            "checks": [{"measurement": "tdb_mg_per_c", "axis": "x", "value": value, "unit": "mg/C", "low": low,
                        "high": high}, {"measurement": "noise", "axis": None, "value": None}]}


def test_individuals_chart_and_cpk_by_hand():
    runs = [_run(i, v, slot=f"s0{i % 2 + 1}") for i, v in enumerate([1.0, 2.0, 3.0, 2.0, 1.0])]
    assert spc.parameters(runs) == ["tdb_mg_per_c:x"]  # a check without a value is no parameter
    r = spc.spc_report(runs, "tdb_mg_per_c:x")
    c = r.chart
    sigma = 1.0 / 1.128
    assert c.mean == pytest.approx(1.8) and c.mr_bar == pytest.approx(1.0) and c.sigma_within == pytest.approx(sigma)
    assert c.ucl == pytest.approx(1.8 + 3 * sigma) and c.lcl == pytest.approx(1.8 - 3 * sigma)
    assert c.mr_ucl == pytest.approx(3.267) and c.out_of_control == []
    cap = r.capability
    assert cap.cpk == pytest.approx(min(5 - 1.8, 1.8 + 1) / (3 * sigma))
    assert cap.ppk == pytest.approx(min(5 - 1.8, 1.8 + 1) / (3 * np.std([1, 2, 3, 2, 1], ddof=1)))
    assert sum(r.histogram.counts) == 5 and r.histogram.edges[0] == -1.0 and r.histogram.edges[-1] == 5.0
    assert [(s.slot, s.n, s.mean) for s in r.slots] == [("s01", 3, pytest.approx(5 / 3)), ("s02", 2, 2.0)]
    # a shift beyond 3 sigma is flagged; one-sided limits give the one side
    runs2 = [_run(i, v, high=None) for i, v in enumerate([0.0, 0.1, 0.0, 0.1, 0.0, 0.1, 3.0])]
    r2 = spc.spc_report(runs2, "tdb_mg_per_c:x")
    assert r2.chart.out_of_control == [6]
    assert r2.capability.cpk == pytest.approx((r2.capability.mean + 1) / (3 * r2.chart.sigma_within))
    assert spc.capability([], None, None, None).cpk is None and spc.individuals([2.0]).ucl is None


def test_yields_by_batch_day_product():
    runs = [_run(1, 0, batch=1, verdict="pass"), _run(2, 0, batch=1, verdict="fail"),
            _run(3, 0, batch=2, verdict="marginal", at="2026-11-21T01:00:00+00:00"),
            _run(4, 0, batch=2, verdict="pass", at="2026-11-21T02:00:00+00:00"), _run(5, 0, batch=2, verdict="error")]
    by_batch = {y.key: y for y in spc.yields(runs, "batch")}
    assert (by_batch["1"].judged, by_batch["1"].passed, by_batch["1"].yield_pct) == (2, 1, 50.0)
    assert (by_batch["2"].marginal, by_batch["2"].errors, by_batch["2"].yield_pct) == (1, 1, pytest.approx(100 / 3))
    assert {y.key: y.judged for y in spc.yields(runs, "day")} == {"2026-11-20": 3, "2026-11-21": 2}  # run 5 on the 20th
    assert [(y.key, y.passed) for y in spc.yields(runs, "product")] == [("LIS3DSH", 2)]


@pytest.fixture(scope="module")
def api_url(tmp_path_factory):
    db = Database(f"sqlite:///{tmp_path_factory.mktemp('spc') / 's.db'}", station="line-2")
    db.upgrade()
    written = write_batches(db, n_batches=3, per_batch=6, seed=11)
    app = create_app(SimpleNamespace(config=None, bus=None, db=db), repo=DbRepository(db),
                     tokens=TokenStore([(TOKEN, "mes", "mes")]), outbox=False)
    url, stop_server = serve_in_thread(app)
    yield url, written
    stop_server()
    db.dispose()


def test_spc_rest_and_csv(api_url):
    url, written = api_url
    h = {"Authorization": f"Bearer {TOKEN}"}
    r = httpx.get(f"{url}/api/spc", params={"parameter": "tdb_mg_per_c:y"}, headers=h, timeout=30)
    assert r.status_code == 200, r.text
    body = r.json()
    values = [w["tdb"][1] for w in written]
    assert [p["value"] for p in body["points"]] == values  # oldest first, every judged run
    mr_bar = float(np.mean(np.abs(np.diff(values))))
    sigma = mr_bar / 1.128
    lim = LIMITS["tdb_mg_per_c"]
    mean = float(np.mean(values))
    assert body["chart"]["ucl"] == pytest.approx(mean + 3 * sigma)
    assert body["capability"]["cpk"] == pytest.approx(min(lim - mean, mean + lim) / (3 * sigma))
    assert body["capability"]["low"] == -lim and body["capability"]["high"] == lim
    assert set(body["parameters"]) == {f"{m}:{ax}" for m in ("tdb_mg_per_c", "tdsf_ppm_per_c") for ax in "xyz"}
    batches = sorted({w["batch"] for w in written})
    by_batch = {int(y["key"]): y for y in body["yield"]["batch"]}
    for b in batches:
        mine = [w for w in written if w["batch"] == b]
        assert by_batch[b]["judged"] == len(mine)
        assert by_batch[b]["passed"] == sum(w["verdict"] == "pass" for w in mine)
    assert [y["key"] for y in body["yield"]["station"]] == ["line-2"]
    print(f"\nSPC tdb_mg_per_c:y over {len(values)} runs: mean {mean:.3f} mg/C, Cpk {body['capability']['cpk']:.2f}, "
          f"Ppk {body['capability']['ppk']:.2f}; yield per batch "
          + ", ".join(f"{b}: {by_batch[b]['yield_pct']:.0f} %" for b in batches))
    r = httpx.get(f"{url}/api/spc.csv", params={"parameter": "tdsf_ppm_per_c:z"}, headers=h, timeout=30)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert len(rows) == len(written) and rows[0]["serial"] == written[0]["serial"]
    assert [float(x["value"]) for x in rows] == [w["tdsf"][2] for w in written] and rows[0]["station"] == "line-2"
    r = httpx.get(f"{url}/api/spc", params={"parameter": "nope"}, headers=h, timeout=30)
    assert r.status_code == 404 and "tdb_mg_per_c:x" in r.json()["detail"]
    assert httpx.get(f"{url}/api/spc", timeout=30).status_code == 401
    assert math.isfinite(httpx.get(f"{url}/api/spc", headers=h, timeout=30).json()["chart"]["mean"])
