"""Yield and SPC (issues 13, 24): the pure core against hand-computed I-MR limits and Cpk, each run rule
against a sequence built to trigger it and a near miss that must not, the Cpk minimum n and its
interval (coverage measured by simulation), points judged by their own limits, groups never mixed,
the failure Pareto, the parameter names; and the REST answers over real HTTP on a database holding
several judged batches (tests/test_records_filters.py: the filters, groups and CSVs over HTTP)."""

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
from station.records import pareto, parameter_names, spc, spc_rules
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

TOKEN = "mes-token-spc-0001"


def _run(i, value, slot="s01", batch=1, verdict="pass", at="2026-11-20T10:00:00+00:00", low=-1.0, high=5.0,
         product="", version="1"):
    return {"run_id": i, "batch_id": batch, "station": "A", "slot": slot, "serial": f"S{i}", "judged_at": at,
            "verdict": verdict, "limits_name": "LIS3DSH", "limits_version": version, "product": product,
            "checks": [{"measurement": "tdb_mg_per_c", "axis": "x", "value": value, "unit": "mg/C", "low": low,
                        "high": high}, {"measurement": "noise", "axis": None, "value": None}]}


def test_individuals_chart_and_cpk_by_hand():
    runs = [_run(i, v, slot=f"s0{i % 2 + 1}") for i, v in enumerate([1.0, 2.0, 3.0, 2.0, 1.0])]
    assert spc.parameters(runs) == ["tdb_mg_per_c:x"]  # a check without a value is no parameter
    r = spc.spc_report(runs, "tdb_mg_per_c:x", min_n=2)  # the hand computation on 5 points
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
    r2 = spc.spc_report(runs2, "tdb_mg_per_c:x", min_n=2)
    assert r2.chart.out_of_control == [6]
    assert r2.capability.cpk == pytest.approx((r2.capability.mean + 1) / (3 * r2.chart.sigma_within))
    assert spc.capability([], None, None, None).cpk is None and spc.individuals([2.0]).ucl is None
    # the contract since issue 24: no Cpk (nor Ppk) from fewer than CPK_MIN_N points, and it says why
    d = spc.spc_report(runs, "tdb_mg_per_c:x").capability
    assert (d.cpk, d.ppk, d.reason, d.min_n) == (None, None, "n=5 < 25", 25)


def test_yields_by_batch_day_product():
    runs = [_run(1, 0, batch=1, verdict="pass"), _run(2, 0, batch=1, verdict="fail"),
            _run(3, 0, batch=2, verdict="marginal", at="2026-11-21T01:00:00+00:00"),
            _run(4, 0, batch=2, verdict="pass", at="2026-11-21T02:00:00+00:00"), _run(5, 0, batch=2, verdict="error")]
    by_batch = {y.key: y for y in spc.yields(runs, "batch")}
    assert (by_batch["1"].judged, by_batch["1"].passed, by_batch["1"].yield_pct) == (2, 1, 50.0)
    assert (by_batch["2"].marginal, by_batch["2"].errors, by_batch["2"].yield_pct) == (1, 1, pytest.approx(100 / 3))
    assert {y.key: y.judged for y in spc.yields(runs, "day")} == {"2026-11-20": 3, "2026-11-21": 2}  # run 5 on the 20th
    assert [(y.key, y.passed) for y in spc.yields(runs, "product")] == [("unspecified product", 2)]
    assert [(y.key, y.passed) for y in spc.yields(runs, "limits")] == [("LIS3DSH v1", 2)]


@pytest.fixture(scope="module")
def api_url(tmp_path_factory):
    db = Database(f"sqlite:///{tmp_path_factory.mktemp('spc') / 's.db'}", station="line-2")
    db.upgrade()
    written = write_batches(db, n_batches=5, per_batch=6, seed=11)  # 30 runs: Cpk from n >= 25
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
    cpk = min(lim - mean, mean + lim) / (3 * sigma)
    assert body["capability"]["cpk"] == pytest.approx(cpk)
    se = math.sqrt(1 / (9 * 30) + cpk ** 2 / (2 * 0.62 * 29))  # Bissell, MR-bar's df, by hand
    assert body["capability"]["cpk_ci_low"] == pytest.approx(cpk - 1.959964 * se, rel=1e-6)
    assert body["capability"]["below_target"] == (cpk < 1.33) and body["capability"]["min_n"] == 25
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
    assert [float(x["value (ppm/°C)"]) for x in rows] == [w["tdsf"][2] for w in written]
    assert rows[0]["station"] == "line-2" and [int(x["#"]) for x in rows] == list(range(1, 31))
    r = httpx.get(f"{url}/api/spc", params={"parameter": "nope"}, headers=h, timeout=30)
    assert r.status_code == 404 and "tdb_mg_per_c:x" in r.json()["detail"]
    assert httpx.get(f"{url}/api/spc", timeout=30).status_code == 401
    assert math.isfinite(httpx.get(f"{url}/api/spc", headers=h, timeout=30).json()["chart"]["mean"])


# ---- run rules: each from its definition, a sequence that triggers it and a near miss -----------------
# mean 0, sigma 1 given: the rules are tested apart from the estimation of the centre and sigma
RULE_CASES = {
    "1": ([0.0, 0.5, 3.01], {2}, [0.0, 0.5, 3.0, -2.99]),  # exactly 3 sigma is not beyond
    "2": ([0.5] * 9, {8}, [0.5] * 4 + [0.0] + [0.5] * 4 + [-0.2] + [0.5] * 8),  # on the centre breaks it
    "3": ([1, 2, 3, 4, 5, 6], {5}, [1, 2, 3, 4, 5, 5, 6, 7, 8, 9]),  # a tie breaks it; 5 rising is not 6
    "4": ([0.1, -0.1] * 7, {13}, [0.1, -0.1] * 6 + [0.1]),  # 13 alternating points are not 14
    "5": ([0.0, 2.1, 0.0, 2.1], {3}, [2.1, 0.0, 0.0, 2.1, -2.1, 0.0, 2.1]),  # 2 beyond but not within 3 / same side
    "6": ([1.1, 1.1, 0.0, 1.1, 1.1], {4}, [1.1, 1.1, 0.0, 0.0, 1.1, 1.1, -1.1, 1.1]),  # 3 of 5 only
    "7": ([0.5, -0.3, 0.2, -1.0, 0.9] * 3, {14}, [0.5, -0.3, 0.2, -1.0, 0.9] * 2 + [0.5, -0.3, 0.2, -1.01, 0.9]),
    "8": ([1.5, -1.5] * 4, {7}, [1.5] * 8 + [0.0] + [1.5, -1.5] * 3 + [1.5, 0.9]),  # one side only; then 7 + one inside
}


@pytest.mark.parametrize("rule", sorted(RULE_CASES))
def test_each_run_rule_triggers_on_its_pattern_and_not_on_a_near_miss(rule):
    hit, expected, miss = RULE_CASES[rule]
    f = spc_rules.RULES[rule]
    assert f(hit, 0.0, 1.0) == expected, (rule, f(hit, 0.0, 1.0))
    assert f(miss, 0.0, 1.0) == set(), (rule, f(miss, 0.0, 1.0))
    # decreasing / the other side is the same rule (mirror image)
    assert f([-v for v in hit], 0.0, 1.0) == expected
    # a longer run keeps flagging every point that continues it (rules 2, 3, 7 and 8 are runs)
    if rule in "2378":
        longer = hit + [hit[-1] + (1 if rule == "3" else 0)] if rule != "8" else hit + [1.5]
        assert f(longer, 0.0, 1.0) == expected | {len(hit)}
    assert spc_rules.RULE_NAMES[rule]


def test_moving_range_flag_and_rule_names_on_the_points():
    # noise of 0.1, then one jump of 2.9: MR 2.9 > D4 * MR-bar; the same series without the jump: no MR flag
    base = [0.0, 0.1] * 6
    assert spc_rules.moving_range_flags(base + [3.0], spc.individuals(base + [3.0]).mr_ucl) == {12}
    assert spc_rules.moving_range_flags(base + [0.0], spc.individuals(base + [0.0]).mr_ucl) == set()
    # a shift of the process: 10 points around 0, then 9 at +0.35: rule 2 on the 9th, named in words
    values = [0.0, 0.1, -0.1, 0.05, -0.05, 0.1, -0.1, 0.0, 0.05, -0.05] + [0.35, 0.3, 0.4, 0.35, 0.3, 0.4, 0.35, 0.3, 0.4]
    r = spc.spc_report([_run(i, v) for i, v in enumerate(values)], "tdb_mg_per_c:x")
    mean = float(np.mean(values))
    sides = [(v > mean) - (v < mean) for v in values]  # independent of spc_rules: 9 in a row, either side
    rule2 = [i for i in range(8, len(values)) if sides[i] != 0 and len(set(sides[i - 8: i + 1])) == 1]
    assert rule2 == [8, 9, 18]  # 9 before the shift below the centre, then the 9 after it above
    assert [i for i, q in enumerate(r.points) if any(f.rule == "2" for f in q.flags)] == rule2
    p = r.points[18]
    assert spc.Flag("2", "9 in a row on one side of the centre line") in p.flags
    assert r.chart.rule_counts["2"] == sum(any(f.rule == "2" for f in q.flags) for q in r.points)
    assert r.chart.flagged == [i for i, q in enumerate(r.points) if q.flags]
    assert "2: 9 in a row on one side of the centre line" in spc.csv_text(r).splitlines()[18 + 1]


# ---- Cpk: minimum n, interval, highlight ---------------------------------------------------------------
def test_cpk_minimum_n_interval_and_highlight():
    rng = np.random.default_rng(4)
    x12 = list(rng.normal(0.0, 0.4, 12))
    c = spc.spc_report([_run(i, v, low=-1.5, high=1.5) for i, v in enumerate(x12)], "tdb_mg_per_c:x").capability
    assert c.cpk is None and c.reason == "n=12 < 25" and c.below_target is None and c.n == 12
    x40 = list(rng.normal(0.3, 0.4, 40))
    r = spc.spc_report([_run(i, v, low=-1.5, high=1.5) for i, v in enumerate(x40)], "tdb_mg_per_c:x")
    c = r.capability
    sigma = np.mean(np.abs(np.diff(x40))) / 1.128
    cpk = min(1.5 - np.mean(x40), np.mean(x40) + 1.5) / (3 * sigma)
    se = math.sqrt(1 / (9 * 40) + cpk ** 2 / (2 * 0.62 * 39))
    assert c.cpk == pytest.approx(cpk) and c.reason is None
    assert (c.cpk_ci_low, c.cpk_ci_high) == (pytest.approx(cpk - 1.959964 * se), pytest.approx(cpk + 1.959964 * se))
    assert c.below_target is True and cpk < 1.33  # a Cpk near 0.9: highlighted
    wide = spc.capability(list(rng.normal(0.0, 0.1, 30)), -1.5, 1.5, 0.1)
    assert wide.cpk == pytest.approx(min(1.5 - wide.mean, wide.mean + 1.5) / 0.3) and wide.below_target is False


def _coverage(rng, n, reps, phi, df_factor=spc.MR_DF_FACTOR):
    """How often the 95 % interval holds the true Cpk (1.0: limits ±3, sigma 1) of an AR(1) process
    with `phi` and marginal sigma 1 (phi 0: independent normal values)."""
    hits = 0
    for _ in range(reps):
        e = rng.normal(0.0, math.sqrt(1 - phi ** 2), n)
        x = np.empty(n)
        x[0] = rng.normal()
        for i in range(1, n):
            x[i] = phi * x[i - 1] + e[i]
        c = spc.capability(list(x), -3.0, 3.0, float(np.mean(np.abs(np.diff(x))) / 1.128), min_n=2)
        lo, hi = spc.cpk_interval(c.cpk, n, df_factor=df_factor)
        hits += lo <= 1.0 <= hi
    return hits / reps


def test_cpk_interval_coverage_by_simulation_and_autocorrelation_makes_it_optimistic():
    rng = np.random.default_rng(24)
    independent = _coverage(rng, 50, 1000, 0.0)
    plain = _coverage(rng, 50, 1000, 0.0, df_factor=1.0)  # Bissell with n - 1, as for the sample sigma
    correlated = _coverage(rng, 50, 300, 0.7)
    print(f"\n95 % interval of Cpk, n=50: coverage {independent:.3f} (MR-bar's df, 1000 runs), {plain:.3f} (n-1), "
          f"{correlated:.3f} AR(1) phi=0.7 (300 runs)")
    assert 0.92 <= independent <= 0.97  # as stated under its assumptions (binomial sd at 1000 runs: 0.007)
    assert plain < independent - 0.02  # why the MR-bar degrees of freedom
    assert correlated < 0.5  # as the docstring warns: far too narrow on autocorrelated data


# ---- own limits, groups --------------------------------------------------------------------------------
def test_each_point_is_judged_by_its_own_limits_not_the_newest():
    """The audit: v1 (USL 1.5) then v2 (USL 1.0). The newest run's limits on every point give 5 out
    of spec; each run's own limits give 2. Cpk only within one version."""
    v1 = [_run(i, v, low=-1.5, high=1.5, version="1") for i, v in enumerate([1.2, 1.2, 1.2, 0.5, 1.6])]
    v2 = [_run(10 + i, v, low=-1.0, high=1.0, version="2", at="2026-11-21T10:00:00+00:00")
          for i, v in enumerate([0.5, 1.1])]
    runs = v1 + v2
    assert sum(r["checks"][0]["value"] > 1.0 for r in runs) == 5  # what the old code counted
    gs = spc.groups(runs)
    assert [(g.limits_version, g.runs) for g in gs] == [("2", 2), ("1", 5)]  # newest first
    reports = [spc.spc_report(spc.in_group(runs, g.key), "tdb_mg_per_c:x", group=g) for g in gs]
    assert sum(r.capability.out_of_spec for r in reports) == 2
    assert [p.spec for p in reports[1].points] == ["in spec"] * 4 + ["above USL"]
    assert [(p.spec, p.high) for p in reports[0].points] == [("in spec", 1.0), ("above USL", 1.0)]
    # one limits version whose limits differ (edited without a version bump): still judged per point,
    # and no Cpk against a mix of limits
    same_version = [dict(r, limits_version="1") for r in runs] * 4
    mixed = spc.spc_report(same_version, "tdb_mg_per_c:x")
    assert mixed.capability.out_of_spec == 8 and mixed.capability.cpk is None
    assert "2 different sets of limits" in mixed.capability.reason


def test_groups_never_mix_products_or_limits_versions():
    runs = ([_run(i, 0.1 * (i % 3), product="ACC-1 rev A", version="1") for i in range(4)]
            + [_run(10 + i, 5.0, product="ACC-2 rev B", version="1", at="2026-11-22T10:00:00+00:00") for i in range(3)]
            + [_run(20 + i, 0.2, product="ACC-1 rev A", version="2", at="2026-11-21T10:00:00+00:00") for i in range(2)])
    view = spc.spc_view(runs)
    assert [g.label for g in view.groups] == ["ACC-2 rev B · LIS3DSH v1", "ACC-1 rev A · LIS3DSH v2",
                                              "ACC-1 rev A · LIS3DSH v1"]
    assert view.report.group.product == "ACC-2 rev B" and [p.run_id for p in view.report.points] == [10, 11, 12]
    for g in view.groups:
        v = spc.spc_view(runs, g.key, "tdb_mg_per_c:x")
        expect = [r["run_id"] for r in runs if (r["product"], r["limits_version"]) == (g.product, g.limits_version)]
        assert [p.run_id for p in v.report.points] == expect
    with pytest.raises(LookupError, match="ACC-1 rev A · LIS3DSH v2"):
        spc.spc_view(runs, "nope")
    with pytest.raises(LookupError, match="known: tdb_mg_per_c:x"):
        spc.spc_view(runs, None, "tdsf_ppm_per_c:z")
    assert spc.group_key(("A|B", "C", "1")) != spc.group_key(("A", "B|C", "1"))  # keys are injective
    assert view.labels == {"tdb_mg_per_c:x": "TDB x (mg/°C)"}


# ---- failure Pareto ------------------------------------------------------------------------------------
def _judged(i, verdict, fails=(), errors=(), state="done", reasons=()):
    checks = [{"measurement": m, "axis": a, "value": 9.0, "outcome": "fail"} for m, a in fails]
    checks += [{"measurement": m, "axis": a, "value": None, "outcome": "error", "reason": f"{a} {m} not measured"}
               for m, a in errors]
    checks += [{"measurement": "bow_mg", "axis": "x", "value": 0.1, "outcome": "marginal"}]
    return {"run_id": i, "verdict": verdict, "state": state, "checks": checks, "reasons": list(reasons)}


def test_failure_pareto_sorted_with_cumulative_percent_and_causes():
    runs = ([_judged(i, "fail", fails=[("tdb_mg_per_c", "x")]) for i in range(5)]
            + [_judged(10 + i, "fail", fails=[("tdsf_ppm_per_c", "z"), ("tdb_mg_per_c", "x")]) for i in range(2)]
            + [_judged(20, "fail", fails=[("lost_samples_pct", None)])]
            + [_judged(30, "error", errors=[("tdb_mg_per_c", "y")])]
            + [_judged(40 + i, "error", state="faulted", reasons=[f"s0{i}: link lost after {i + 2}.5 s"]) for i in range(3)]
            + [_judged(50 + i, "error", reasons=[f"timeout after {10 + i} s"]) for i in range(2)]
            + [_judged(60, "pass")])
    p = pareto.pareto(runs)
    assert (p.runs, p.runs_failed, p.runs_error) == (15, 8, 6)
    got = [(r.rank, r.what, r.fail, r.error, r.count, r.pct, r.cum_pct) for r in p.checks]
    assert got == [(1, "TDB x", 7, 0, 7, 63.6, 63.6), (2, "TDSF z", 2, 0, 2, 18.2, 81.8),  # 11 failing checks
                   (3, "lost samples", 1, 0, 1, 9.1, 90.9), (4, "TDB y", 0, 1, 1, 9.1, 100.0)]  # marginal: not counted
    # one cause per run judged fail or error, by name (station/records/causes.py): a fail by the
    # measurement that failed it, an error by the station's words; unknown words keep their text
    assert [(r.what, r.fail, r.error, r.count, r.cum_pct) for r in p.causes] == [
        ("limit: TDB", 5, 0, 5, 35.7), ("link lost", 0, 3, 3, 57.1), ("limit: TDSF", 2, 0, 2, 71.4),
        ("timeout after N s", 0, 2, 2, 85.7), ("limit: lost samples", 1, 0, 1, 92.9), ("not measured", 0, 1, 1, 100.0)]
    assert p.causes[1].example == "s00: link lost after 2.5 s"
    rows = list(csv.reader(io.StringIO(pareto.csv_text(p))))
    assert rows[0] == list(pareto.CSV_COLUMNS) and rows[1] == ["checks", "1", "TDB x", "7", "0", "7", "63.6", "63.6"]
    assert rows[-1] == ["causes", "6", "not measured", "0", "1", "1", "7.1", "100.0"]


# ---- parameter names -----------------------------------------------------------------------------------
def test_every_measurement_the_verdicts_use_has_words_and_a_unit():
    from station.decisions import limits as L
    from station.decisions import verdicts as V

    axes = {ax: {"tdb_mg_per_c": 0.1, "tdsf_ppm_per_c": -50.0} for ax in "xyz"}
    residual = {ax: {k: 0.1 for k in ("drift_error_fs_pct", "drift_error_mg", "bow_mg", "ramp_residual_rms_mg",
                                      "noise_ug_per_sqrt_hz")} for ax in "xyz"}
    made = (V.thermal_measurements({"axes": axes, "streaming": {"axes": axes}, "residual": {"axes": residual}})
            + V.sfem_measurements({"bias": [0.01] * 3, "scale": [1.001] * 3})
            + V.link_measurements({"samples_lost": 1}, 100)
            + V.program_measurements({"programmed": True, "crc": "ab", "readback_crc": "ab", "comp": 1})
            + V.verification_measurements({"e_after_fs_pct": {"x": 0.1}, "axes": {"x": {"passed": True}}}))
    names = {m.name for m in made}
    names |= {lim.measurement for spec in L.default_products().values() for lim in spec.limits}
    names |= {g.measurement for spec in L.default_products().values() for gr in spec.grades for g in gr.limits}
    names |= {r if isinstance(r, str) else r.measurement for a in ("thermal", "sfem", "none")
              for r in V.profile_requirements(a, program_verify=True)}
    assert len(names) >= 17
    missing = sorted(names - set(parameter_names.WORDS))
    assert missing == [], f"no words for {missing}"
    assert parameter_names.label("tdb_mg_per_c:x") == "TDB x (mg/°C)"
    assert parameter_names.label("tdsf_ppm_per_c:z") == "TDSF z (ppm/°C)"
    assert parameter_names.label("noise_ug_per_sqrt_hz:y") == "noise density y (µg/√Hz)"
    assert parameter_names.label("site_thing_mg:x", "mg/C") == "site thing mg x (mg/°C)"  # unknown: still words
