"""`station replay` (issue 16): a recorded batch, or logs, through simulated boards, diffed.

Independent truth: the recorded database rows (results, verdicts, sample chunks in counts), the
replay boards' CRC of what they put on the wire, and logs from tests/replay_logs.py, a generator
that shares no code with the station's simulator.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from replay_logs import write_logs

SPEED = "300"
SERIALS_OF_DEMO = [f"SIM{i:04d}" for i in range(1, 13)]


def _station(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 12-DUT demo batch (8 serial + 4 CAN) recorded by the real daemon into SQLite. Without the
    demo's MES stand-in: the part it holds would never be tested, and a run that tested no part
    (like a label mismatch) is not replayed, so 11 DUTs would replay."""
    folder = tmp_path_factory.mktemp("replay")
    url = f"sqlite:///{folder / 'line.db'}"
    out = _station("demo", "--once", "--serial", "8", "--can", "4", "--speed", SPEED, "--db", url, "--no-mes")
    assert out.returncode == 0, out.stdout + out.stderr
    return folder, url


def _db(url: str):
    from station.daemon.storage import open_database

    return open_database(url, station="test")


def _tight_limits(folder: Path, rec) -> tuple[Path, list[str], list[str], dict]:
    """A config whose TDSF floor two of the recorded passing parts miss by far and two meet by far
    (chosen among the parts recorded `pass`: a part the recording judged marginal stays marginal)."""
    tdsf = {d.serial: min(d.outcome["thermal"][ax]["tdsf_ppm_per_c"] for ax in "xyz") for d in rec.duts
            if d.outcome["verdict"] == "pass"}
    assert len(tdsf) >= 4, {d.serial: d.outcome["verdict"] for d in rec.duts}
    chosen = sorted(tdsf, key=tdsf.get)
    worst, best = chosen[:2], chosen[-2:]
    floor = (tdsf[worst[1]] + tdsf[best[0]]) / 2
    assert tdsf[worst[1]] < floor - 30 and tdsf[best[0]] > floor + 30, tdsf
    cfg = folder / "tight.toml"
    limits = f'[[products.{{sensor}}.limits]]\nmeasurement = "tdsf_ppm_per_c"\nlow = {floor:.1f}\nlabel = "TDSF"\n'
    cfg.write_text(
        'name = "tight"\n[lamp]\ntcp = {host = "127.0.0.1", port = 1502}\nunit = 1\n'
        '[[slots]]\nname = "s01"\nserial = "/dev/null"\n'
        + "".join(f'[products.{s}]\nsensor = "{s}"\nversion = "tight-1"\n' + limits.format(sensor=s)
                  for s in sorted({d.identity.sensor for d in rec.duts}))
    )
    return cfg, worst, best, tdsf


@pytest.fixture(scope="module")
def replays(recorded):
    """The recorded batch replayed as it was, then with a tighter limits set (4 DUTs)."""
    from station.replay.recording import from_database

    folder, url = recorded
    out = {}
    out["same"] = _station("replay", "--db", url, "--batch", "1", "--speed", SPEED, "--json", str(folder / "same.json"))
    cfg, worst, best, tdsf = _tight_limits(folder, from_database(url, 1))
    out["tight"] = _station("replay", "--db", url, "--batch", "1", "--speed", SPEED, "--config", str(cfg),
                            "--only", *worst, *best, "--json", str(folder / "tight.json"))
    return out, {"worst": worst, "best": best, "tdsf": tdsf}


def test_a_recorded_12_dut_demo_batch_replays_identically(recorded, replays):
    from db import repository as R
    from db.export import run_samples
    from contracts.recording import to_counts
    from station.replay.recording import from_database

    folder, url = recorded
    out = replays[0]["same"]
    assert out.returncode == 0, out.stdout + out.stderr
    diff = json.loads((folder / "same.json").read_text())
    assert diff["summary"]["duts"] == 12 and diff["summary"]["unchanged"] == 12, diff["summary"]
    for d in diff["duts"]:
        assert d["samples_identical"] is True, d
        assert d["compared"] >= 15, d  # 12 thermal numbers (2 methods) at least, plus the words
    assert "12 unchanged, 0 changed" in out.stdout
    assert diff["agreement"]["lamp"]["agrees"] and diff["agreement"]["fixture"]["agrees"], diff["agreement"]

    db = _db(url)
    try:
        rec = from_database(url, 1)
        replay_id = diff["replay_batch_id"]
        replay = R.batch_detail(db, replay_id)
        assert replay["replay_of"].startswith("batch 1 of ") and replay["replay_diff"]["summary"]["unchanged"] == 12
        by_slot = {r["slot"]: r for r in replay["runs"]}
        assert {d.slot for d in rec.duts} == set(by_slot)
        for d in rec.duts:
            run = by_slot[d.slot]
            # the samples the daemon stored from the replay board, back in counts, are the recorded ones
            smp = run_samples(db, run["id"])
            acc, tc = to_counts(d.identity, smp.acc_g, smp.temp_c, d.slot)
            n = len(smp)
            # every sample the fit uses (up to the run's last segment) was replayed and stored;
            # what the recording holds after it depends on how late its daemon stopped the boards
            segs = R.segments_of_run(db, run["id"])
            t_last = max(g["t_end_s"] for g in segs)
            assert n >= int(np.searchsorted(d.time_s, t_last, side="right")) and len(segs) >= 4
            np.testing.assert_array_equal(acc, d.acc_counts[:n])
            np.testing.assert_array_equal(tc, d.temp_counts[:n])
            np.testing.assert_array_equal(smp.time_s, d.time_s[:n])
            # stored as a replay: no MES cursor, the recorded attempt's number
            assert run["result_seq"] is None and run["attempt"] == 1 and run["verdict"] == d.outcome["verdict"]
        # the MES sees the 12 recorded results only; yields count the 12 real attempts only
        results = R.results_since(db, 0, 1000)
        assert sorted(r["batch_id"] for r in results) == [1] * 12
        y = R.yields(db)
        assert y["duts"] == 12 and y["attempts"] == 12
        assert all(r["batch_id"] == 1 for r in R.judged_runs(db))
    finally:
        db.dispose()


def test_a_changed_limits_set_lists_the_changed_verdicts_and_exits_1(recorded, replays):
    folder, _ = recorded
    out, parts = replays[0]["tight"], replays[1]
    worst, best = parts["worst"], parts["best"]
    assert out.returncode == 1, out.stdout + out.stderr
    diff = json.loads((folder / "tight.json").read_text())
    changed = {v["serial"]: (v["before"], v["after"]) for v in diff["summary"]["verdicts_changed"]}
    assert changed == {s: ("pass", "fail") for s in worst}, (changed, parts["tdsf"])
    assert {d["serial"] for d in diff["duts"]} == set(worst + best)
    for s in worst:
        assert f"verdict changed: {s} pass -> fail" in out.stdout
    for d in diff["duts"]:  # the science did not change, only the judgement
        assert not [c for c in d["changes"] if c["key"].startswith(("offline.", "streaming."))], d


CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)")
def test_the_page_lists_replays_and_shows_the_changed_verdicts(recorded, replays):
    sync_api = pytest.importorskip("playwright.sync_api")
    from web.app import create_app
    from web.auth import TokenStore
    from web.db_repo import DbRepository
    from web_support import IdleStation, serve_in_thread

    _, url = recorded
    worst = replays[1]["worst"]
    db = _db(url)
    app = create_app(IdleStation(db), repo=DbRepository(db), outbox=False,
                     tokens=TokenStore([("operator-token-replay", "operator", "ana")]))
    base, stop_server = serve_in_thread(app)
    artifacts = Path(__file__).resolve().parents[1] / "artifacts"
    artifacts.mkdir(exist_ok=True)
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                         args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 1400})
                page.set_default_timeout(20_000)
                page.goto(base + "/")
                page.fill("#token", "operator-token-replay")
                page.click("#save-token")
                page.click("#tab-records")
                page.wait_for_selector("#replay-table tr[data-batch] >> nth=1")
                rows = page.locator("#replay-table tr[data-batch]")
                texts = [rows.nth(i).inner_text() for i in range(rows.count())]
                tight = next(t for t in texts if "fail" in t)
                for s in worst:
                    assert f"{s} pass → fail" in tight, texts
                assert any("none" in t and "agrees" in t for t in texts), texts  # the identical replay
                rows.filter(has_text=worst[0]).first.click()
                page.wait_for_selector(f"#replay-changes tr[data-serial='{worst[0]}']")
                cell = page.locator(f"#replay-changes tr[data-serial='{worst[0]}'] td").nth(3).inner_text()
                assert "verdict pass → fail" in cell, cell
                page.screenshot(path=str(artifacts / "browser-replays.png"), full_page=True)
            finally:
                browser.close()
    finally:
        stop_server()
        db.dispose()


def test_replay_of_csv_logs_from_an_independent_generator(tmp_path):
    paths, truths = write_logs(tmp_path / "logs", 3)
    out_json = tmp_path / "logs.json"
    url = f"sqlite:///{tmp_path / 'replay.db'}"
    out = _station("replay", "--logs", *map(str, paths), "--db", url, "--speed", SPEED, "--json", str(out_json))
    assert out.returncode == 0, out.stdout + out.stderr
    diff = json.loads(out_json.read_text())
    assert diff["before"] == "offline fit of the log" and diff["summary"]["unchanged"] == 3, diff["summary"]
    assert all(d["samples_identical"] for d in diff["duts"])
    assert "lamp" in diff["agreement"] and "fixture" in diff["agreement"]  # the logs carry both columns
    from db import repository as R

    db = _db(url)
    try:
        runs = {r["serial"]: r for r in R.batch_detail(db, diff["replay_batch_id"])["runs"]}
        for t in truths:
            with db.session() as s:
                th = R._run_results(s, runs[t.serial]["id"])["thermal_by_method"]["offline"]
            tdb = np.array([th[ax]["tdb_mg_per_c"] for ax in "xyz"])
            tdsf = np.array([th[ax]["tdsf_ppm_per_c"] for ax in "xyz"])
            # white noise 0.2 mg over ~14k samples: measured |error| <= 0.004 mg/C and 0.6 ppm/C
            np.testing.assert_allclose(tdb, t.tdb_mg_per_c, atol=0.015)
            np.testing.assert_allclose(tdsf, t.tdsf_ppm_per_c, atol=2.5)
    finally:
        db.dispose()


def test_replay_source_mistakes_are_one_line(tmp_path, recorded):
    _, url = recorded
    for args, text in ((("--db", url, "--batch", "99"), "no batch 99"),
                       (("--db", url, "--batch", "1", "--only", "NOPE"), "NOPE not in the recording"),
                       (("--logs", str(tmp_path / "missing.csv")), "missing.csv"),
                       ((), "exactly one source")):
        out = _station("replay", *args, timeout=60)
        assert out.returncode == 2, (args, out.stderr)
        lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and text in lines[0] and "Traceback" not in out.stderr, (args, out.stderr)
