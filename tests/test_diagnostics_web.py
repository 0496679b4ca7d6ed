"""Model diagnostics of a stored run over REST (issue 6): JSON, plots, the model, the page's panel."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

import diag_helpers as H
from station.diagnostics.effects import smooth_temperature
from station.diagnostics.model import DiagnosticModel
from web.app import create_app
from web.auth import TokenStore
from web.repo import NoRepository

TOKEN = "diag-op-token-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class OneRunRepo(NoRepository):
    """Run 1 holds a simulated single-ramp-rate log with a hidden bias_t2; run 2 has no log."""

    def __init__(self, log):
        self.log = log
        self.log_reads = 0

    def run(self, run_id):
        return {"id": run_id, "serial": self.log.serial} if run_id in (1, 2) else None

    def run_log(self, run_id):
        if run_id != 1:
            return None
        self.log_reads += 1
        return self.log


@pytest.fixture(scope="module")
def client():
    logs, truths = H.sim_logs(("bias_t2",), profile=H.SINGLE_RATE, seed=7)
    repo = OneRunRepo(logs[0])
    app = create_app(SimpleNamespace(config=None, bus=None, db=None), repo=repo,
                     tokens=TokenStore([(TOKEN, "operator", "op")]), outbox=False)
    with TestClient(app) as c:
        c.repo, c.truth = repo, truths[0]
        yield c


def test_diagnosis_json_ranks_the_hidden_effect_and_add_updates_the_staircase(client):
    r = client.get("/api/runs/1/diagnosis", headers=AUTH)
    assert r.status_code == 200, r.text
    doc = r.json()
    assert set(doc) >= {"baseline", "ranking", "model", "staircase", "confusable", "unidentifiable", "plots", "library"}
    assert doc["ranking"][0]["effect"] == "bias_t2" and doc["ranking"][0]["admitted"]
    assert [s["model"] for s in doc["staircase"]] == ["baseline"]
    assert {e["effect"] for e in doc["library"]} >= {"bias_t2", "thermal_lag", "hysteresis"}
    # the engineer clicks bias_t2, then bias_t3: the staircase grows, the error falls
    r2 = client.get("/api/runs/1/diagnosis", params=[("add", "bias_t2"), ("add", "bias_t3")], headers=AUTH)
    assert r2.status_code == 200, r2.text
    st = r2.json()["staircase"]
    assert [s["model"] for s in st] == ["baseline", "+bias_t2", "+bias_t3"]
    assert st[1]["heldout_rms_mg"] < 0.2 * st[0]["heldout_rms_mg"]
    c2 = r2.json()["model"]["parameters"][client.truth.serial]["effects"]["bias_t2"]["c2_mg_per_c2"]
    for i, ax in enumerate("xyz"):
        assert abs(c2[ax]["value"] - client.truth.effects["bias_t2"]["c2_mg_per_c2"][i]) < 1e-3
    # cached: asking again does not refit (or re-read the log)
    reads = client.repo.log_reads
    assert client.get("/api/runs/1/diagnosis", params=[("add", "bias_t2"), ("add", "bias_t3")], headers=AUTH).status_code == 200
    assert client.repo.log_reads == reads


def test_diagnosis_plots_are_pngs(client):
    for plot in ("staircase", "ranking", "residual_vs_temperature"):
        r = client.get(f"/api/runs/1/diagnosis/{plot}.png", params={"add": "bias_t2"}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "image/png" and r.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert client.get("/api/runs/1/diagnosis/nonsense.png", headers=AUTH).status_code == 404


def test_diagnosis_plots_are_rendered_once_and_the_caches_are_bounded(client):
    """Issue 10: plots were rendered on every request. A repeat is served from the PNG cache
    (same bytes, no render); both caches stay within their sizes."""
    pngs = client.app.state.diagnosis_cache.pngs
    first = client.get("/api/runs/1/diagnosis/ranking.png", params={"add": "bias_t2"}, headers=AUTH)
    rendered = pngs.computed
    again = client.get("/api/runs/1/diagnosis/ranking.png", params={"add": "bias_t2"}, headers=AUTH)
    assert again.status_code == 200 and again.content == first.content
    assert pngs.computed == rendered
    cache = client.app.state.diagnosis_cache
    assert len(cache.reports) <= cache.reports.size and len(pngs) <= pngs.size


def test_model_download_compensates(client):
    r = client.get("/api/runs/1/diagnosis/model.json", params={"add": "bias_t2"}, headers=AUTH)
    assert r.status_code == 200, r.text
    model = DiagnosticModel.from_json(r.json())
    assert model.effects == ["bias_t2"]
    log = client.repo.log
    comp = model.compensate(log.time_s, log.acc_g, log.temp_c)
    # compensated readings of one orientation no longer depend on temperature (bias_t2 included)
    sel = log.position == log.position[-1]  # the second orientation: 20 -> 50 -> 20 C
    smooth = smooth_temperature(log.temp_c, log.time_s, 300.0)  # select on the temperature, not its noise
    hot, cold = sel & (smooth > 45), sel & (smooth < 25)
    assert hot.sum() > 500 and cold.sum() > 500
    drift_mg = (comp[hot].mean(axis=0) - comp[cold].mean(axis=0)) * 1000
    raw_mg = (log.acc_g[hot].mean(axis=0) - log.acc_g[cold].mean(axis=0)) * 1000
    assert np.max(np.abs(drift_mg)) < 0.2 and np.max(np.abs(raw_mg)) > 5


def test_errors_and_auth(client):
    assert client.get("/api/runs/1/diagnosis").status_code == 401
    r = client.get("/api/runs/1/diagnosis", params={"add": "nonsense"}, headers=AUTH)
    assert r.status_code == 422 and "nonsense" in r.json()["detail"]
    for blank in ("", " bias_t2"):  # the schema's enum: exact names only (schemathesis found `add=` accepted)
        r = client.get("/api/runs/1/diagnosis", params={"add": blank}, headers=AUTH)
        assert r.status_code == 422 and "unknown effect" in r.json()["detail"], (blank, r.text)
    assert client.get("/api/runs/2/diagnosis", headers=AUTH).status_code == 404
    assert client.get("/api/runs/99/diagnosis", headers=AUTH).status_code == 404


def test_page_has_the_panel_and_its_script(client):
    html = client.get("/").text
    assert 'src="/static/diagnose.js"' in html and 'id="diag-panel"' in html
    js = client.get("/static/diagnose.js").text
    assert "/diagnosis" in js and "diagnoseRun" in js
    assert "diagnoseRun" in client.get("/static/app.js").text


@pytest.mark.browser
def test_page_panel_adds_an_effect_with_a_click_and_the_staircase_updates(client):
    """Headless Chromium: open the panel for run 1, click bias_t2, see the staircase grow."""
    import shutil
    import threading
    import time

    sync_api = pytest.importorskip("playwright.sync_api")
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("chromium is not installed")
    import uvicorn

    from web_support import free_port

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(client.app, host="127.0.0.1", port=port, log_level="critical"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        for _ in range(100):
            if server.started:
                break
            time.sleep(0.05)
        url = f"http://127.0.0.1:{port}/"
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                         args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
            try:
                page = browser.new_page(viewport={"width": 1200, "height": 1600})
                errors = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(url)
                page.evaluate(f"localStorage.setItem('station.token', '{TOKEN}')")
                page.goto(url)
                page.click("#tab-history")
                page.evaluate("diagnoseRun(1, 'SIM0001')")  # what the run card's Diagnose button calls
                page.wait_for_selector("button[data-effect=bias_t2]", timeout=60_000)
                assert page.locator("#diag-staircase tr").count() == 2  # header + baseline
                page.click("button[data-effect=bias_t2]")
                for _ in range(240):
                    if page.locator("#diag-staircase tr").count() == 3:
                        break
                    page.wait_for_timeout(250)
                text = page.inner_text("#diag-staircase")
                assert "+bias_t2" in text, text
                assert "bias_t2.c2_mg_per_c2" in page.inner_text("#diag-params")
                assert "✓ bias_t2" in page.inner_text("#diag-effects")
                page.wait_for_selector("#diag-plots img", timeout=30_000)
                assert errors == []
            finally:
                browser.close()
    finally:
        server.should_exit = True
        thread.join(timeout=10)
