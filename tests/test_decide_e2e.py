"""The station decides, end to end: a simulated batch (serial boards on ptys, Modbus lamp/fixture on
127.0.0.1, SQLite) whose spec limits are set from the SIMULATOR'S TRUTH so that the parts straddle
them; each DUT's verdict and grade is checked against what the truth says it must be:

    fail      the DUT whose true TDSF lies 40+ ppm/C below the TDSF limit (named, with value/limit/unit)
    marginal  the DUT whose true TDB IS the TDB limit: its 2-sigma interval crosses it (sigma = the
              fit's (+) the limit's systematic u_sys)
    pass A/B  the two others, split by a grade-A TDB limit half-way between their true TDBs
    error     a DUT whose board disconnects mid-batch (never pass)
    fail      a DUT with a quadratic bias drift (bias_t2): "curvature bow (linear model rejected, N sigma)"

then a retest of the same serials (attempt 2, aborted: error) and the yields.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from drivers.sim.physics import draw_population
from drivers.sim.station_sim import SimStation
from cli.commands.demo import sim_config
from station.config import parse_config
from station.decisions.limits import default_products
from station.daemon.storage import open_database
from station.daemon.supervisor import Station

SPEED = 400.0
SEED = 3
N = 6
FAULTED, CURVED = 4, 5  # indices: board 4 disconnects, board 5 has the bias_t2 effect
GAP_TDSF_PPM = 40.0  # true distance of every DUT from the TDSF limit (the fit's sigma is ~1 ppm/C)
GAP_TDB_MG = 0.05  # true distance from the TDB limits for the non-marginal DUTs (sigma ~0.0005)


def population():
    truths = draw_population(N, SEED, effects=("bias_t2",))
    for i, t in enumerate(truths):
        if i != CURVED:
            t.effects = {}
    return truths


def limits_from_truth(truths):
    """Roles and a product spec whose limits straddle the true parameters (asserting the gaps)."""
    linear = [i for i in range(N) if i not in (FAULTED, CURVED)]
    min_tdsf = {i: float(np.min(truths[i].tdsf_ppm_per_c)) for i in linear}
    fail = min(linear, key=min_tdsf.get)
    rest = sorted(min_tdsf[i] for i in linear if i != fail)
    assert rest[0] - min_tdsf[fail] > 2 * GAP_TDSF_PPM, "seed gives no clear TDSF failure"
    tdsf_limit = min_tdsf[fail] + GAP_TDSF_PPM
    others = [i for i in linear if i != fail]
    max_tdb = {i: float(np.max(truths[i].tdb_mg_per_c)) for i in others}
    marginal = max(others, key=max_tdb.get)
    tdb_limit = max_tdb[marginal]  # the truth sits ON the limit
    passing = sorted((i for i in others if i != marginal), key=max_tdb.get)
    assert len(passing) == 2
    assert max_tdb[passing[1]] < tdb_limit - GAP_TDB_MG
    grade_a_high = 0.5 * (max_tdb[passing[0]] + max_tdb[passing[1]])
    assert max_tdb[passing[1]] - max_tdb[passing[0]] > 2 * GAP_TDB_MG
    lo = min(float(np.min(t.tdb_mg_per_c)) for t in truths) - 0.3
    base = default_products()["LIS3DSH"].model_dump(mode="json")
    base["limits"] = [lim for lim in base["limits"] if lim["measurement"] not in ("tdb_mg_per_c", "tdsf_ppm_per_c")]
    base["limits"] += [
        {"measurement": "tdb_mg_per_c", "low": lo, "high": tdb_limit, "unit": "mg/C", "label": "TDB", "required": True,
         "u_sys": 1e-3},
        {"measurement": "tdsf_ppm_per_c", "low": tdsf_limit, "unit": "ppm/C", "label": "TDSF", "required": True,
         "u_sys": 2.0},
    ]
    base["grades"] = [{"name": "A", "tray": "A tray", "limits": [{"measurement": "tdb_mg_per_c", "low": lo, "high": grade_a_high}]},
                      {"name": "B", "tray": "B tray"}]
    base.update(name="test-straddle", version="3", guard_sigma=2.0)
    # bow (residual.py: |c2| R^2 / 8): the linear DUTs' true bow is 0 (measured ~0.2-1.6 mg +- 0.2-0.6,
    # die lag and noise), the curved DUT's true bow is 2+ mg over the limit
    bow_limit = 4.0
    for lim in base["limits"]:
        if lim["measurement"] == "bow_mg":
            lim["high"] = bow_limit
    c2 = np.abs(truths[CURVED].effects["bias_t2"]["c2_mg_per_c2"])
    assert float(np.max(c2)) * base["operating_range_c"] ** 2 / 8 > bow_limit + 2.0
    roles = {"fail": fail, "marginal": marginal, "pass_a": passing[0], "pass_b": passing[1]}
    return roles, base, tdsf_limit


@pytest.mark.timeout(420)  # a hang guard: under CI load the simulated plant waits for a busy daemon (backpressure)
async def test_verdicts_against_the_truth_then_a_retest(tmp_path):
    truths = population()
    roles, product, tdsf_limit = limits_from_truth(truths)
    async with SimStation(n_serial=N, seed=SEED, speed=SPEED, truths=truths) as sim:
        data = sim_config(sim, speed=SPEED, db_url=f"sqlite:///{tmp_path / 'station.db'}")
        data["products"] = {"LIS3DSH": product}
        cfg = parse_config(data, "<test>")
        db = open_database(cfg.database_url)
        st = Station(cfg, db=db)
        await st.start()
        try:
            bid = st.start_batch("fast-thermal", None, "pytest")

            async def unplug():
                while st.batch_status(bid)["step_index"] < 1:
                    await asyncio.sleep(0.05)
                sim.board(FAULTED).disconnect()

            plug = asyncio.create_task(unplug())
            status = await st.wait_batch(bid, timeout_s=300)
            await plug
            assert status["state"] == "finished", status["error"]
            by = {s["slot"]: s for s in status["slots"]}
            slot = {i: f"s{i + 1:02d}" for i in range(N)}
            dec = {i: by[slot[i]]["decision"] for i in range(N)}

            d = dec[roles["fail"]]
            assert (d["verdict"], d["grade"], d["tray"]) == ("fail", "reject", "reject"), d["reasons"]
            k = int(np.argmin(truths[roles["fail"]].tdsf_ppm_per_c))
            ax = "xyz"[k]
            named = [f for f in d["failures"] if f["measurement"] == "tdsf_ppm_per_c" and f["outcome"] == "fail"]
            assert [f["axis"] for f in named] == [ax]
            assert named[0]["low"] == pytest.approx(tdsf_limit) and named[0]["unit"] == "ppm/C"
            assert named[0]["value"] == pytest.approx(truths[roles["fail"]].tdsf_ppm_per_c[k], abs=10)
            assert any(r.startswith(f"{ax} TDSF ") and r.endswith(f"limit {tdsf_limit:.0f}") for r in d["reasons"]), d["reasons"]

            d = dec[roles["marginal"]]
            assert (d["verdict"], d["grade"]) == ("marginal", "hold"), d["reasons"]
            assert len(d["reasons"]) == 1 and "TDB" in d["reasons"][0] and "crosses limit" in d["reasons"][0]

            for role, grade, tray in (("pass_a", "A", "A tray"), ("pass_b", "B", "B tray")):
                d = dec[roles[role]]
                assert (d["verdict"], d["grade"], d["tray"]) == ("pass", grade, tray), (role, d["reasons"])

            d = dec[FAULTED]
            assert by[slot[FAULTED]]["state"] == "faulted"
            assert (d["verdict"], d["grade"], d["tray"]) == ("error", "retest", "retest")
            assert "link lost" in d["reason"]

            d = dec[CURVED]
            assert d["verdict"] == "fail"
            bows = [f for f in d["failures"] if f["measurement"] == "bow_mg" and f["outcome"] == "fail"]
            assert bows, d["reasons"]
            assert any("curvature bow (linear model rejected" in r for r in d["reasons"]), d["reasons"]

            assert all(dec[i]["attempt"] == 1 and dec[i]["limits_name"] == "test-straddle"
                       and dec[i]["limits_version"] == "3" for i in range(N))
            assert status["decision"]["verdicts"] == {"pass": 2, "marginal": 1, "fail": 2, "error": 1}
            assert {e["slot"]: e["tray"] for e in status["sorting"]}[slot[roles["pass_a"]]] == "A tray"

            # stored per run, and in the MES feed with the same verdicts
            await st.flush_db()
            from db.repository import dut_by_serial, results_since, runs_of_dut, yields
            from web.mes_outbox import payload_of

            feed = {r["serial"]: r for r in results_since(db, 0, 100)}
            assert len(feed) == N
            for i in range(N):
                r = feed[truths[i].serial]
                assert (r["verdict"], r["grade"], r["attempt"], r["limits_version"]) == (
                    dec[i]["verdict"], dec[i]["grade"], 1, "3")
                p = payload_of({**r, "idempotency_key": "k"}, "st")
                assert (p["verdict"], p["grade"], p["attempt"], p["limits_name"]) == (dec[i]["verdict"], dec[i]["grade"], 1,
                                                                                     "test-straddle")
                assert p["reason"] == dec[i]["reason"]

            # retest of the same serials: attempt 2 (aborted after connecting -> error)
            bid2 = st.start_batch("fast-thermal", None, "pytest")
            loop = asyncio.get_running_loop()
            end = loop.time() + 60
            while not all(s["run_id"] for s in st.batch_status(bid2)["slots"] if s["slot"] != slot[FAULTED]):
                late = st.batch_status(bid2)
                assert loop.time() < end and late["state"] not in ("finished", "failed", "aborted"), (
                    "the retest's DUTs never all got a run: "
                    f"{[(s['slot'], s['state'], s['run_id'], s.get('fault_reason')) for s in late['slots']]} "
                    f"batch {late['state']}: {late['error']}")
                await asyncio.sleep(0.05)
            st.abort(bid2, "operator")
            status2 = await st.wait_batch(bid2, timeout_s=90)
            assert status2["state"] == "aborted"
            for s in status2["slots"]:
                if s["slot"] == slot[FAULTED]:
                    continue
                assert (s["decision"]["verdict"], s["decision"]["attempt"]) == ("error", 2), s["decision"]
                assert "aborted" in s["decision"]["reason"]
            await st.flush_db()
            serial = truths[roles["pass_a"]].serial
            runs = runs_of_dut(db, serial)
            assert [(r["attempt"], r["verdict"]) for r in runs] == [(2, "error"), (1, "pass")]
            dut = dut_by_serial(db, serial)  # the latest VALID attempt is the DUT's result
            assert (dut["attempt"], dut["verdict"], dut["grade"], dut["attempts"]) == (1, "pass", "A", 2)
            y = yields(db)
            assert (y["duts"], y["first_pass"], y["final_pass"]) == (N, 2, 2)
            assert y["first_pass_yield"] == pytest.approx(2 / N)
        finally:
            await st.close()
            db.dispose()
