"""Model diagnostics of a stored run over REST (issue 6): JSON, plots, the model, the page's panel.

Issue 38: every plot (residual vs orientation too) is served, in the page's order, and rendered
ahead as soon as the report is computed (no plot request needed), within the PNG cache's limits;
the JSON says every flag in words and names the orientations as the CLI does."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

import diag_helpers as H
import web.diag_plots as diag_plots
from station.diagnostics.effects import smooth_temperature
from station.diagnostics.model import DiagnosticModel
from station.diagnostics.plots import PLOTS, figure, flag_words
from station.diagnostics.ranking import diagnose
from web.app import create_app
from web.auth import TokenStore
from web.diag_plots import PAGE_PLOTS, BoundedCache, DiagnosisCache
from web.repo import NoRepository
from web.schemas_diagnosis import Leftover, LeftoverAxis, LeftoverView
from web_support import wait_for

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
def sim_log():
    logs, truths = H.sim_logs(("bias_t2",), profile=H.SINGLE_RATE, seed=7)
    return logs[0], truths[0]


def _app(log, cache: DiagnosisCache | None = None):
    repo = OneRunRepo(log)
    app = create_app(SimpleNamespace(config=None, bus=None, db=None), repo=repo,
                     tokens=TokenStore([(TOKEN, "operator", "op")]), outbox=False)
    if cache is not None:
        app.state.diagnosis_cache = cache
    return app, repo


@pytest.fixture(scope="module")
def client(sim_log):
    app, repo = _app(sim_log[0])
    with TestClient(app) as c:
        c.repo, c.truth = repo, sim_log[1]
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
    doc = client.get("/api/runs/1/diagnosis", params={"add": "bias_t2"}, headers=AUTH).json()
    # every plot, the new residual vs orientation too, in the page's order
    assert "residual_vs_orientation" in PLOTS and sorted(doc["plots"]) == sorted(PLOTS)
    assert doc["plots"][:2] == ["staircase", "ranking"] and list(PAGE_PLOTS) == doc["plots"]
    for plot in doc["plots"]:
        r = client.get(f"/api/runs/1/diagnosis/{plot}.png", params={"add": "bias_t2"}, headers=AUTH)
        assert r.status_code == 200, (plot, r.text)
        assert r.headers["content-type"] == "image/png" and r.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert client.get("/api/runs/1/diagnosis/nonsense.png", headers=AUTH).status_code == 404


def test_the_json_says_flags_in_words_and_names_orientations_as_the_cli(client):
    doc = client.get("/api/runs/1/diagnosis", headers=AUTH).json()
    serial = client.truth.serial
    # the log's positions 0 and 1, as `station diagnose` names them (noise_view._position_name)
    assert doc["orientations"] == {serial: [{"label": "0", "name": "position 0 (P)"},
                                            {"label": "1", "name": "position 1 (N)"}]}
    assert any(r["flags"] for r in doc["ranking"]), doc["ranking"]
    raw = ("no_evidence", "confusable_with:", "explained_by:", "stands_for_it:", "masked:")
    for r in doc["ranking"]:
        assert r["flags_text"] == [flag_words(f) for f in r["flags"]], r
        for t in r["flags_text"]:
            assert not any(x in t for x in raw), t
    # the leftover statement (station/diagnostics/leftover.py), when the report has one, is served
    # as it is and every key of it is declared (the page shows its statement first)
    lo = doc.get("leftover")
    if lo:
        assert isinstance(lo["statement"], str) and isinstance(lo["above_floor"], bool)
        assert set(lo) <= set(Leftover.model_fields), set(lo) - set(Leftover.model_fields)
        for v in lo.get("views", []):
            assert set(v) <= set(LeftoverView.model_fields), v
        for axes in lo.get("per_dut", {}).values():
            for a in axes.values():
                assert set(a) <= set(LeftoverAxis.model_fields), a


def test_flag_words():
    assert flag_words("no_evidence") == "no evidence on its own against the baseline"
    assert flag_words("confusable_with:hysteresis") == "confusable with hysteresis on this data"
    assert flag_words("explained_by:bias_t2,thermal_lag") == "explained by bias_t2 and thermal_lag, admitted before it"
    assert flag_words("stands_for_it:thermal_lag").startswith("thermal_lag, admitted, stands for it")
    assert flag_words("masked:evidence_given:bias_t2") == "its evidence shows only once bias_t2 is in the model"
    assert flag_words("masked:admitted_with:hysteresis").startswith("admitted together with hysteresis")
    assert flag_words("at_bound:tau_s = 10 s at its lower bound") == "at bound: tau_s = 10 s at its lower bound"


def test_plots_colour_by_orientation_and_direction_and_the_ranking_says_words(sim_log):
    """The figures themselves (pure: report in, Figure out): the legend names each orientation as
    the CLI does and heating / cooling; residual vs orientation has a box per orientation; the
    ranking bars carry words, not flags."""
    rep = diagnose([sim_log[0]], add=["bias_t2"])
    for name in ("residual_vs_temperature", "residual_vs_rate", "residual_vs_time"):
        fig = figure(rep, name)
        labels = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
        assert "position 0 (P)" in labels and "position 1 (N)" in labels, (name, labels)
        assert any(x.startswith("heating") for x in labels) and any(x.startswith("cooling") for x in labels), labels
        assert "baseline residual" in labels  # an effect was added: the baseline's residual in grey behind
    fig = figure(rep, "residual_vs_orientation")
    ticks = [t.get_text() for t in fig.axes[-1].get_xticklabels()]
    assert ticks == ["position 0 (P)", "position 1 (N)"]
    assert len(fig.axes) == 3 and all(len(ax.patches) >= 4 for ax in fig.axes)  # 2 boxes + 2 baseline boxes per axis
    texts = " ".join(t.get_text() for ax in figure(rep, "ranking").axes for t in ax.texts)
    assert "admitted" in texts
    for raw in ("no_evidence", "confusable_with", "explained_by", "stands_for_it", "masked:"):
        assert raw not in texts, texts


def test_plots_are_rendered_ahead_once_the_report_is_computed(sim_log, monkeypatch):
    """Issue 38: the page asks for the plots only once it shows the ranking; rendered then, they came
    seconds after it. Now the report's computation queues them at once, in the page's order, and
    the page's requests find them ready: each plot rendered once, no request needed."""
    order: list[tuple[object, str]] = []
    real = diag_plots.plot_png

    def recording(rep, name):
        order.append((rep, name))
        return real(rep, name)

    monkeypatch.setattr(diag_plots, "plot_png", recording)
    cache = DiagnosisCache()
    app, _ = _app(sim_log[0], cache)
    with TestClient(app) as c:
        doc = c.get("/api/runs/1/diagnosis", headers=AUTH).json()
        keys = [(1, (), name) for name in doc["plots"]]
        wait_for(lambda: all(cache.pngs.has(k) and cache.pngs.running == 0 for k in keys), 60, 0.05,
                 "every plot rendered ahead")
        rep = cache.reports.get((1, ()), lambda: None)  # cached: the report this app computed
        assert [n for r, n in order if r is rep] == doc["plots"] and cache.pngs.computed == len(doc["plots"])
        for name in doc["plots"]:
            r = c.get(f"/api/runs/1/diagnosis/{name}.png", headers=AUTH)
            assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
        assert cache.pngs.computed == len(doc["plots"]) and cache.pngs.refused == 0  # served from the cache
        assert cache.ahead.rendered == len(doc["plots"]) and cache.ahead.pending == 0


def test_render_ahead_stays_within_the_plot_limits():
    """prefetch never waits and is never refused: it skips a key cached or being computed, and any
    key when every slot is taken; a request for a key it computes waits for that computation."""
    cache: BoundedCache[bytes] = BoundedCache("plot", size=4, max_running=1, max_waiting=1)
    assert cache.prefetch("a", lambda: b"A") is True and cache.get("a", lambda: b"other") == b"A"
    assert cache.prefetch("a", lambda: b"again") is False and cache.computed == 1
    release, started = threading.Event(), threading.Event()

    def slow():
        started.set()
        release.wait(10)
        return b"B"

    t = threading.Thread(target=cache.prefetch, args=("b", slow), daemon=True)
    t.start()
    assert started.wait(5)
    assert cache.prefetch("c", lambda: b"C") is False  # the only slot is taken: skipped, not queued
    assert cache.prefetch("b", lambda: b"x") is False  # being computed
    got: list[bytes | None] = []
    waiter = threading.Thread(target=lambda: got.append(cache.get("b", lambda: b"twice")), daemon=True)
    waiter.start()
    time.sleep(0.1)
    release.set()
    t.join(5)
    waiter.join(5)
    assert got == [b"B"] and cache.computed == 2 and cache.refused == 0 and not cache.has("c")

    # the render-ahead thread holds the plots of at most PRERENDER_REPORTS reports, the newest first
    dc = DiagnosisCache(prerender=2)
    gate = threading.Event()
    done: list[str] = []

    def job(name):
        def run():
            gate.wait(10)
            done.append(name)
            return name.encode()
        return run

    dc.ahead.submit("r1", [(("r1", n), job(f"r1.{n}")) for n in range(3)])
    wait_for(lambda: dc.pngs.running == 1, 5, 0.01, "r1's first plot rendering")
    dc.ahead.submit("r2", [(("r2", n), job(f"r2.{n}")) for n in range(2)])
    dc.ahead.submit("r3", [(("r3", n), job(f"r3.{n}")) for n in range(2)])
    assert dc.ahead.dropped == 1  # r1's remaining plots: the engineer has clicked past it
    gate.set()
    wait_for(lambda: dc.ahead.pending == 0 and dc.pngs.running == 0, 10, 0.01, "render-ahead idle")
    assert done == ["r1.0", "r3.0", "r3.1", "r2.0", "r2.1"], done


def test_diagnosis_plots_are_rendered_once_and_the_caches_are_bounded(client):
    """Issue 10: plots were rendered on every request. A repeat is served from the PNG cache
    (same bytes, no render); both caches stay within their sizes."""
    first = client.get("/api/runs/1/diagnosis/ranking.png", params={"add": "bias_t2"}, headers=AUTH)
    pngs = client.app.state.diagnosis_cache.pngs  # made at the first diagnosis request
    ahead = client.app.state.diagnosis_cache.ahead  # plots rendered ahead of the page: let it finish
    wait_for(lambda: ahead.pending == 0 and pngs.running == 0, 60, 0.05, "render-ahead idle")
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
