"""The model-diagnostics panel in headless Chromium under load shedding (web/diag_plots.py).

The server is built with the smallest limits (one diagnosis and one plot computed at a time, nobody
waiting) and another client holds the diagnosis slot when the panel opens, so the page meets real
429 answers: for the diagnosis JSON and, with two plots in flight, for the plots. The panel must
queue its plots, wait the Retry-After the server asks for, say in words what each request waits
for, and in the end show every plot with no "busy" left on screen; every candidate in the ranking
says why it is (not) admitted. The screenshot goes to tmp_path and /tmp/diag_panel.png.

Issue 38: words, never labels: no raw flag (no_evidence, confusable_with:...) anywhere on the panel,
each flag in words under the candidate's why, the orientations named as the CLI names them
("position 0 (P)"), and the leftover statement first, above the ranking, when the report has one.
"""

from __future__ import annotations

import re
import shutil
import threading
import time
from types import SimpleNamespace

import httpx
import pytest

import diag_helpers as H
import web.diag_plots as diag_plots
from web.app import create_app
from web.auth import TokenStore
from web.diag_plots import DiagnosisCache
from web.repo import NoRepository
from web_support import CHROMIUM, chromium_page, serve_in_thread, wait_for

TOKEN = "diag-browser-token-0123"
SCREENSHOT_COPY = "/tmp/diag_panel.png"
WAITING_COPY = "/tmp/diag_panel_waiting.png"
PLOT_RENDER_EXTRA_S = 0.4  # each plot renders this much longer: the second one in flight meets a 429

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]


class OneRunRepo(NoRepository):
    """Run 1: a simulated single-ramp-rate log with a hidden bias_t2 (as tests/test_diagnostics_web.py)."""

    def __init__(self, log):
        self.log = log

    def run(self, run_id):
        return {"id": run_id, "serial": self.log.serial} if run_id == 1 else None

    def run_log(self, run_id):
        return self.log if run_id == 1 else None


# Every text the panel's status line and plot states show, as they change (the waits last ~1 s).
RECORD_STATES = """
window.__diagSeen = new Set();
document.addEventListener("DOMContentLoaded", () => {
  const note = () => {
    const st = document.getElementById("diag-status");
    if (st && st.textContent) window.__diagSeen.add("status: " + st.textContent);
    for (const s of document.querySelectorAll("#diag-plots .diag-plot-state")) {
      if (s.textContent) window.__diagSeen.add("plot: " + s.textContent);
    }
  };
  new MutationObserver(note).observe(document.body, { subtree: true, childList: true, characterData: true });
});
"""

ALL_PLOTS_LOADED = """n => {
  const figs = [...document.querySelectorAll('#diag-plots figure.diag-plot')];
  return figs.length === n && figs.every(f => {
    const img = f.querySelector('img');
    return f.dataset.state === 'loaded' && img && img.complete && img.naturalWidth > 0;
  });
}"""


def test_diagnosis_panel_retries_429_and_explains_every_candidate(tmp_path, monkeypatch):
    pytest.importorskip("playwright.sync_api")
    t_start = time.monotonic()
    logs, _ = H.sim_logs(("bias_t2",), profile=H.SINGLE_RATE, seed=7)
    app = create_app(SimpleNamespace(config=None, bus=None, db=None), repo=OneRunRepo(logs[0]),
                     tokens=TokenStore([(TOKEN, "operator", "op")]), outbox=False)
    cache = app.state.diagnosis_cache = DiagnosisCache(max_running=1, max_running_plots=1, max_waiting=0)
    real_png = diag_plots.plot_png

    def slow_png(rep, name):
        time.sleep(PLOT_RENDER_EXTRA_S)
        return real_png(rep, name)

    monkeypatch.setattr(diag_plots, "plot_png", slow_png)

    # another client's diagnosis holds the only diagnosis slot until released
    release = threading.Event()
    holder = threading.Thread(target=lambda: cache.reports.get(("other client",), lambda: release.wait(30) and None,
                                                               store=False), daemon=True)
    holder.start()
    wait_for(lambda: cache.reports.running == 1, 5, 0.01, "the other diagnosis runs")

    url, stop_server = serve_in_thread(app)
    shot = tmp_path / "diag_panel.png"
    try:
        with chromium_page(1400, 1000, timeout_ms=20_000) as (page, errors):
            responses: list[tuple[str, int]] = []
            inflight = {"now": 0, "max": 0}

            def on_request(r):
                if r.url.endswith(".png") or ".png?" in r.url:
                    inflight["now"] += 1
                    inflight["max"] = max(inflight["max"], inflight["now"])

            def on_done(r):
                if r.url.endswith(".png") or ".png?" in r.url:
                    inflight["now"] -= 1

            page.on("request", on_request)
            page.on("requestfinished", on_done)
            page.on("requestfailed", on_done)
            page.on("response", lambda r: responses.append((r.url, r.status)) if "/diagnosis" in r.url else None)
            page.add_init_script(f"localStorage.setItem('station.token', {TOKEN!r});")
            page.add_init_script(RECORD_STATES)
            page.goto(url + "/")
            page.click("#tab-history")
            # what a run's Diagnose button calls (not awaited: the diagnosis waits for the other client)
            page.evaluate("() => { diagnoseRun(1, 'SIM0001'); }")

            # the diagnosis JSON meets 429: the status says it waits, with the elapsed time
            page.wait_for_function(
                "() => /busy with other diagnoses: waiting \\d+ s before try \\d+ of \\d+ · \\d+ s$/"
                ".test(document.getElementById('diag-status').textContent)", timeout=15_000)
            assert page.get_attribute("#diag-status", "data-state") == "working"
            assert cache.reports.refused >= 1
            release.set()
            holder.join(10)

            page.wait_for_selector("#diag-ranking tr[data-effect]", timeout=45_000)
            # a look at the plots while they queue and wait (for a human; not asserted)
            try:
                page.wait_for_selector('#diag-plots figure[data-state="waiting"]', timeout=10_000)
                page.locator("#diag-plots").screenshot(path=str(tmp_path / "diag_plots_waiting.png"))
                shutil.copyfile(tmp_path / "diag_plots_waiting.png", WAITING_COPY)
            except Exception:  # noqa: BLE001 - the waits are short; the assertions below decide
                pass
            n_plots = len(diag_plots.PLOTS)
            try:
                page.wait_for_function(ALL_PLOTS_LOADED, arg=n_plots, timeout=45_000)
            except Exception:
                page.screenshot(path=str(tmp_path / "diag_failed.png"), full_page=True)
                states = page.eval_on_selector_all("#diag-plots figure", "fs => fs.map(f => [f.dataset.plot, "
                                                   "f.dataset.state, f.innerText])")
                raise AssertionError(f"not every plot loaded: {states}; errors {errors}")

            # every plot listed by the diagnosis is on the page, as a decoded image
            doc = httpx.get(f"{url}/api/runs/1/diagnosis", headers={"Authorization": f"Bearer {TOKEN}"},
                            timeout=30).json()
            shown = page.eval_on_selector_all("#diag-plots figure", "fs => fs.map(f => f.dataset.plot)")
            assert shown == doc["plots"]  # in the server's order: the order it renders them in ahead
            assert "residual_vs_orientation" in shown
            widths = page.eval_on_selector_all("#diag-plots img", "is => is.map(i => i.naturalWidth)")
            assert len(widths) == len(doc["plots"]) and min(widths) > 0

            # the server refused plot requests (429), the page waited and retried: each plot
            # rendered exactly once, never more than two plot requests in flight
            plot_429 = [u for u, s in responses if s == 429 and ".png" in u]
            assert cache.pngs.refused >= 1 and plot_429, (cache.pngs.refused, responses)
            assert cache.pngs.computed == n_plots
            assert inflight["max"] <= 2, inflight
            for name in doc["plots"]:
                assert any(s == 200 and f"/{name}.png" in u for u, s in responses), name
            seen = page.evaluate("[...window.__diagSeen]")
            assert any(re.fullmatch(r"plot: station busy, retrying in \d+ s \(try \d+ of \d+\)", s) for s in seen), seen
            assert any(s.startswith("plot: queued") for s in seen), seen
            assert any(s.startswith("plot: rendering") for s in seen), seen
            assert any(s.startswith("status: fitting the models") for s in seen), seen

            # nothing busy or failed left on screen
            panel_text = page.inner_text("#diag-panel")
            for word in ("busy", "429", "retry", "retrying", "failed", "gave up", "queued", "rendering"):
                assert word not in panel_text.lower(), (word, panel_text)
            assert page.locator("#diag-panel .error").count() == 0

            # the ranking: every candidate says in words why it is (not) in the model
            rows = page.locator("#diag-ranking tr[data-effect]")
            assert rows.count() == len(doc["ranking"]) >= 2
            for r in doc["ranking"]:
                tr = page.locator(f'#diag-ranking tr[data-effect="{r["effect"]}"]')
                why = " ".join(tr.locator("td.diag-why .diag-reason").inner_text().split())
                # each flag in words under the reason (the server's flags_text), never the label
                if r["flags"]:
                    words = " ".join(tr.locator("td.diag-why .diag-flagwords").inner_text().split())
                    assert words == " ".join(" · ".join(r["flags_text"]).split()), (r["effect"], words)
                else:
                    assert tr.locator("td.diag-why .diag-flagwords").count() == 0
                if r.get("why"):
                    assert why == " ".join(r["why"].split()), (r["effect"], why)
                elif r["admitted"]:
                    assert why.startswith("admitted"), (r["effect"], why)
                else:
                    assert why.startswith("not admitted: ") and len(why) > len("not admitted: ") + 10, (r["effect"], why)
                if not r["admitted"]:
                    assert why and why != "no", r["effect"]
                if r.get("shape"):
                    assert r["shape"] in tr.locator("td.diag-name").inner_text()
            not_admitted = [r for r in doc["ranking"] if not r["admitted"]]
            assert not_admitted, doc["ranking"]
            # the reasons derived in the page name the gate that failed, with the numbers
            derived = {r["effect"]: " ".join(page.locator(f'#diag-ranking tr[data-effect="{r["effect"]}"] td.diag-why .diag-reason')
                                             .inner_text().split()) for r in not_admitted if not r.get("why")}
            for r in not_admitted:
                if r.get("why") or any(f.split(":")[0] in ("explained_by", "stands_for_it") for f in r["flags"]):
                    continue
                text = derived[r["effect"]]
                if r["delta_bic"] >= -30:
                    assert f"delta BIC {r['delta_bic']:.1f} >= -30" in text, text
                if r["heldout_gain_rel"] < 0.03:
                    assert "does not lower the held-out error by 3 %" in text and " mg)" in text, text
            for r in not_admitted:
                for f in r["flags"]:
                    if f.startswith("explained_by:") and not r.get("why"):
                        assert "explained by " + f.split(":", 1)[1].replace(",", " and ") in derived[r["effect"]]

            # words, never labels: no flag label anywhere on the panel (the tooltips included)
            assert any(r["flags"] for r in doc["ranking"]), doc["ranking"]
            panel_html = page.inner_html("#diag-panel")
            for raw in ("no_evidence", "confusable_with:", "explained_by:", "stands_for_it:", "masked:"):
                assert raw not in panel_text and raw not in panel_html, raw
            assert not re.search(r"orientation o\d", panel_html), "an orientation by its cluster label"
            # the orientations as the CLI names them
            assert page.inner_text("#diag-orientations") == "Orientations in this run: position 0 (P), position 1 (N)"
            # the leftover statement: first, above the effects and the ranking, when the report has one
            lo = doc.get("leftover") or {}
            leftover_text = " ".join(page.inner_text("#diag-leftover").split())
            if lo.get("statement"):
                assert leftover_text.startswith(" ".join(lo["statement"].split())), leftover_text
                top = page.eval_on_selector("#diag-leftover", "e => e.getBoundingClientRect().top")
                assert top < page.eval_on_selector("#diag-effects", "e => e.getBoundingClientRect().top")
                assert top < page.eval_on_selector("#diag-ranking", "e => e.getBoundingClientRect().top")
                assert page.get_attribute("#diag-leftover", "data-above") == ("yes" if lo["above_floor"] else "no")
            else:
                assert leftover_text == "" and not page.is_visible("#diag-leftover")

            # noise you can see: the Allan-deviation statement of the served JSON, on the page
            noise_text = " ".join(page.locator("#diag-noise").inner_text().split())
            statement = " ".join(next(iter(doc["noise"].values()))["statement"].split())
            assert noise_text == "Noise: " + statement and len(statement) > 40, noise_text

            # the wording of the derived reasons and row.why / row.shape, on synthetic rows
            checks = page.evaluate("""() => {
              const doc = { baseline: { heldout_rms_mg: 11.2 } };
              return {
                why: diagReason({ effect: "a", admitted: false, flags: [], why: "told by the backend" }, doc),
                bic: diagReason({ effect: "a", admitted: false, flags: ["no_evidence"], delta_bic: -12.3,
                                  score_p: 1e-9, heldout_gain_rel: 0.1, heldout_rms_mg: 10 }, doc),
                p: diagReason({ effect: "a", admitted: false, flags: ["no_evidence"], delta_bic: -50,
                                score_p: 0.02, heldout_gain_rel: 0.1, heldout_rms_mg: 10 }, doc),
                gain: diagReason({ effect: "a", admitted: false, flags: ["no_evidence"], delta_bic: -434,
                                   score_p: 1e-98, heldout_gain_rel: -0.027, heldout_rms_mg: 11.5 }, doc),
                stands: diagReason({ effect: "a", admitted: false, flags: ["stands_for_it:b", "confusable_with:b"],
                                     delta_bic: -434, score_p: 1e-98, heldout_gain_rel: 0.2, heldout_rms_mg: 9 }, doc),
                admitted: diagReason({ effect: "a", admitted: true, flags: [] }, doc),
              };
            }""")
            assert checks["why"] == "told by the backend"
            assert "not enough evidence in sample (delta BIC -12.3 >= -30)" in checks["bic"]
            assert "likelihood-ratio p = 0.020 >= 0.001 under the correlated-noise model" in checks["p"]
            assert checks["gain"] == ("not admitted: fits in sample but does not lower the held-out error by 3 % "
                                      "(held-out error 11.2 -> 11.5 mg)")
            assert "b, admitted, stands for it" in checks["stands"] and "confusable with b" in checks["stands"]
            assert checks["admitted"] == "admitted"

            # flags in words on rows without flags_text, and the leftover with and without a statement
            words = page.evaluate("""() => ({
              none: diagFlagWords("no_evidence"),
              conf: diagFlagWords("confusable_with:thermal_lag,hysteresis"),
              expl: diagFlagWords("explained_by:bias_t2"),
              stands: diagFlagWords("stands_for_it:thermal_lag"),
              given: diagFlagWords("masked:evidence_given:bias_t2"),
              other: diagFlagWords("at_bound:tau_s = 10 s at its lower bound"),
              row: diagFlagTexts({ flags: ["no_evidence", "explained_by:x"] }),
              orient: [diagOrientationName({}, "6"), diagOrientationName({}, "o1"),
                       diagOrientationName({ orientations: { S: [{ label: "0", name: "position 0 (P)" }] } }, "0")],
            })""")
            assert words["none"] == "no evidence on its own against the baseline"
            assert words["conf"] == "confusable with thermal_lag and hysteresis on this data"
            assert words["expl"] == "explained by bias_t2, admitted before it"
            assert words["stands"].startswith("thermal_lag, admitted, stands for it")
            assert words["given"] == "its evidence shows only once bias_t2 is in the model"
            assert words["other"] == "at bound: tau_s = 10 s at its lower bound"
            assert words["row"] == ["no evidence on its own against the baseline", "explained by x, admitted before it"]
            assert words["orient"] == ["position 6 (+z)", "orientation o1", "position 0 (P)"]
            lo_checks = page.evaluate("""() => {
              const box = document.getElementById("diag-leftover");
              const keep = [...box.childNodes], keepCls = box.className, keepAbove = box.dataset.above;
              diagLeftover({ plots: ["residual_vs_orientation"], leftover: { statement: "An unexplained residual remains.",
                above_floor: true, carrying: ["residual_vs_orientation"] } });
              const shown = box.innerText;
              const above = box.dataset.above;
              diagLeftover({ plots: [] });                      // a report without a leftover
              const absent = box.innerText;
              diagLeftover({ leftover: {} });                   // an empty one
              const empty = box.innerText;
              box.replaceChildren(...keep); box.className = keepCls;
              if (keepAbove !== undefined) box.dataset.above = keepAbove;
              return { shown, above, absent, empty };
            }""")
            assert lo_checks["shown"].startswith("An unexplained residual remains.")
            assert "Look at: residual vs orientation" in lo_checks["shown"] and lo_checks["above"] == "yes"
            assert lo_checks["absent"] == "" and lo_checks["empty"] == ""

            page.locator("#diag-panel").scroll_into_view_if_needed()
            page.locator("#diag-panel").screenshot(path=str(shot))
            shutil.copyfile(shot, SCREENSHOT_COPY)
            assert errors == [], errors
    finally:
        release.set()
        stop_server()
    assert shot.stat().st_size > 10_000
    assert time.monotonic() - t_start < 60
