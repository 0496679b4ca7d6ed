"""The operator page in real headless Chromium (Debian's package, driven by Playwright).

A whole simulated station without a motorized fixture, so the sequencer asks the operator to turn
the plate. From the page only: paste the token, choose the profile and three of four slots, start
the batch, watch the slots update live, confirm both "turn the plate" prompts by clicking, and read
the final TDB/TDSF of every DUT; then the history view: search a serial, open its runs and a plot.
Screenshots go to artifacts/ (CI keeps them).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import httpx
import pytest

from web_support import TOKENS, LiveStation, auth

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]

SELECTED = ["s1", "s2", "c1"]


def card(page, slot):
    return page.locator(f'.slot-card[data-slot="{slot}"]')


def test_operator_runs_a_batch_from_the_page(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    with LiveStation(tmp_path, n_serial=3, n_can=1, speed=250.0, fixture=False, operator_hands=True) as live, \
            sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                     args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
        try:
            page = browser.new_page(viewport={"width": 1366, "height": 900}, has_touch=True)
            foreign, errors = [], []
            page.on("request", lambda r: None if r.url.startswith((live.url, "blob:", "data:")) else foreign.append(r.url))
            page.on("pageerror", lambda e: errors.append(str(e)))
            requested = []
            page.on("request", lambda r: requested.append(r.url))
            page.set_default_timeout(20_000)
            page.goto(live.url + "/")

            # log in with a token, choose profile and slots
            page.fill("#token", TOKENS["operator"])
            page.click("#save-token")
            page.wait_for_selector("#slot-picks input[value='s3']")
            page.select_option("#profile", "fast-thermal")
            # the chosen profile is described: what it is, how many steps, what it yields
            desc = page.inner_text("#profile-desc")
            assert "martinez2022" in desc and "4 steps" in desc and "TDB/TDSF" in desc, desc
            # the long descriptions do not widen the page beyond the screen
            assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
            page.fill("#operator", "Ana")
            page.locator("#slot-picks input[value='s3']").uncheck()
            for slot in SELECTED:
                assert page.locator(f"#slot-picks input[value='{slot}']").is_checked()
            page.click("#start")

            page.wait_for_selector("#batch-panel:not(.hidden)")
            batch_id = int(page.inner_text("#batch-id"))
            with httpx.Client(base_url=live.url, timeout=10) as api:
                st = api.get(f"/api/batches/{batch_id}", headers=auth("operator")).json()
            assert [s["slot"] for s in st["slots"]] == SELECTED and st["operator"] == "Ana"

            # first prompt: the plate to P; the operator turns it and confirms on the page
            page.wait_for_selector("#prompt-banner:not(.hidden)")
            assert "turn the plate" in page.inner_text("#prompt-text")
            page.wait_for_function("() => document.querySelector('#batch-waiting').textContent === 'operator'")
            page.screenshot(path=str(ARTIFACTS / "browser-prompt.png"))
            page.click("#prompt-confirm")
            page.wait_for_selector("#prompt-banner.hidden", state="attached")

            # the slots update live: sample counts grow and segments get logged
            samples = card(page, "s1").locator(".samples")
            page.wait_for_function("() => Number(document.querySelector('.slot-card[data-slot=\"s1\"] .samples').textContent) > 0")
            first = int(samples.inner_text())
            page.wait_for_function(
                f"() => Number(document.querySelector('.slot-card[data-slot=\"s1\"] .samples').textContent) > {first}")
            page.wait_for_function("() => Number(document.querySelector('.slot-card[data-slot=\"c1\"] .segments').textContent) >= 1",
                                   timeout=60_000)
            assert card(page, "s1").get_attribute("data-state") == "running"
            assert card(page, "s3").get_attribute("data-state") != "running"  # not chosen

            # second prompt: turn the plate to N
            page.wait_for_function("() => /turn the plate to N/.test(document.querySelector('#prompt-text').textContent)"
                                   " && !document.querySelector('#prompt-banner').classList.contains('hidden')",
                                   timeout=90_000)
            page.screenshot(path=str(ARTIFACTS / "browser-prompt-N.png"))
            page.click("#prompt-confirm")

            # the batch ends; every chosen DUT shows TDB/TDSF per axis, matching the API
            page.wait_for_function("() => document.querySelector('#batch-state').textContent === 'finished'",
                                   timeout=120_000)
            for slot in SELECTED:
                page.wait_for_selector(f'.slot-card[data-slot="{slot}"] table.results td.tdb', timeout=30_000)
                page.wait_for_function(
                    f"() => {{ const i = document.querySelector('.slot-card[data-slot=\"{slot}\"] img.plot-thumb');"
                    " return i && i.complete && i.naturalWidth > 0; }")
            page.wait_for_function(
                "() => " + " && ".join(f"document.querySelector('.slot-card[data-slot=\"{s}\"]').dataset.state === 'done'"
                                       for s in SELECTED))
            assert len(live.prompts_answered) == 2
            with httpx.Client(base_url=live.url, timeout=10) as api:
                st = api.get(f"/api/batches/{batch_id}", headers=auth("operator")).json()
                assert st["state"] == "finished"
                for s in st["slots"]:
                    c = card(page, s["slot"])
                    assert c.get_attribute("data-state") == "done"
                    assert s["serial"] in c.inner_text()
                    dut = api.get(f"/api/duts/{s['serial']}", headers=auth("operator")).json()
                    for ax in "xyz":
                        row = c.locator(f'table.results tr[data-axis="{ax}"]')
                        shown_tdb = float(row.locator("td.tdb").inner_text())
                        tdsf_text = row.locator("td.tdsf").inner_text()
                        shown_tdsf = float(tdsf_text.split()[0])
                        # a clamped TDSF is flagged on the card as in the API, never a bare 0.0
                        assert ("clamped" in tdsf_text) == bool(dut["thermal"][ax].get("tdsf_clamped")), tdsf_text
                        assert shown_tdb == pytest.approx(dut["thermal"][ax]["tdb_mg_per_c"], abs=0.0006)
                        assert shown_tdsf == pytest.approx(dut["thermal"][ax]["tdsf_ppm_per_c"], abs=0.06)
                    # the part's own 1 sigma, labelled, as the API stores it
                    sig = c.locator(".result .sigmas").inner_text()
                    assert sig.startswith("± 1σ (this part's): TDB "), sig
                    shown = [float(v) for v in sig.split("TDB ")[1].split(" ·")[0].split(" / ")]
                    assert shown == pytest.approx([dut["thermal"][ax]["tdb_sigma_mg_per_c"] for ax in "xyz"], abs=6e-5)
            assert "Fault" not in page.inner_text("#slots")
            for slot in SELECTED:  # progress dots: every step of the profile done
                assert card(page, slot).locator(".dot.on").count() == 4
            page.screenshot(path=str(ARTIFACTS / "browser-results.png"), full_page=True)

            # history: search by part of a serial, every run of the DUT, a plot of a run
            serial = st["slots"][0]["serial"]
            page.click("#tab-history")
            page.fill("#search", serial[-3:])
            page.press("#search", "Enter")
            page.click(f'button.dut[data-serial="{serial}"]')
            run_cards = page.locator("#dut-runs .run-card")
            run_cards.first.wait_for()
            assert run_cards.count() == 1
            assert re.search(rf"Run {st['slots'][0]['run_id']}\b", run_cards.first.inner_text())
            assert run_cards.first.locator("table.results tr[data-axis]").count() == 3
            page.wait_for_function("() => { const i = document.querySelector('#dut-runs img.plot-inline');"
                                   " return i && i.complete && i.naturalWidth > 500; }")
            page.screenshot(path=str(ARTIFACTS / "browser-history.png"), full_page=True)
            run_cards.first.locator("button.plot").click()
            page.wait_for_function("() => { const i = document.querySelector('#plot-img');"
                                   " return i && i.complete && i.naturalWidth > 500; }")
            page.screenshot(path=str(ARTIFACTS / "browser-plot.png"))

            # a second batch, aborted from the page (two taps) while it waits for the operator
            page.click("#plot-dialog button")
            page.click("#tab-live")
            page.click("#new-batch")
            page.click("#start")
            page.wait_for_function(f"() => Number(document.querySelector('#batch-id').textContent) > {batch_id}")
            second = int(page.inner_text("#batch-id"))
            page.wait_for_selector("#prompt-banner:not(.hidden)")
            page.click("#abort")
            assert page.inner_text("#abort") == "Tap again to abort"
            page.click("#abort")
            page.wait_for_function("() => document.querySelector('#batch-state').textContent === 'aborted'")
            page.wait_for_selector("#prompt-banner.hidden", state="attached")
            with httpx.Client(base_url=live.url, timeout=10) as api:
                st2 = api.get(f"/api/batches/{second}", headers=auth("operator")).json()
            assert st2["state"] == "aborted" and st2["lamp_on"] is False
            # after the abort nothing runs, the error says who and when, and each interrupted DUT
            # shows the plot of its own run of this batch (by run id)
            # the person at the page (X-Operator) and the kiosk's token
            page.wait_for_function("() => /aborted by Ana \\(token test-operator\\) at \\d{4}-/.test("
                                   "document.querySelector('#batch-error').textContent)")
            page.wait_for_function(f"() => document.querySelector('#batch-counts').textContent"
                                   f" === '0 running · 0 done · 0 faulted · {len(st2['slots'])} interrupted'")
            for s in st2["slots"]:
                page.wait_for_function(
                    f"() => {{ const i = document.querySelector('.slot-card[data-slot=\"{s['slot']}\"] img.plot-thumb');"
                    " return i && i.complete && i.naturalWidth > 0; }")
                assert f"{live.url}/api/runs/{s['run_id']}/plot.png" in requested
                # the plot of that run, loaded once the run was stored to its end (never half a run)
                alt = card(page, s["slot"]).locator("img.plot-thumb").get_attribute("alt")
                assert alt == f"plot of {s['serial']} run {s['run_id']} (interrupted)", alt
            page.screenshot(path=str(ARTIFACTS / "browser-aborted.png"), full_page=True)
            # the ended batch stays on top; the start form is one tap away ("New batch")
            assert page.is_visible("#new-batch") and page.is_hidden("#start")
            # the same page on the line's small panel PC screen (800x480): nothing wider than it
            page.set_viewport_size({"width": 800, "height": 480})
            page.wait_for_timeout(200)
            assert page.evaluate("() => document.documentElement.scrollWidth") <= 800
            assert page.is_visible("#batch-counts") and page.is_visible("#new-batch")
            page.screenshot(path=str(ARTIFACTS / "browser-aborted-800x480.png"))
            page.set_viewport_size({"width": 1280, "height": 800})
            page.screenshot(path=str(ARTIFACTS / "browser-aborted-1280x800.png"))

            # the API reference is the station's own page too (no Swagger UI from a CDN)
            page.goto(live.url + "/docs")
            page.wait_for_function("() => document.querySelectorAll('.api-op').length >= 15")
            assert "/api/batches/{batch_id}/prompt" in page.inner_text("#api-paths")
            page.screenshot(path=str(ARTIFACTS / "browser-api-docs.png"))

            assert not foreign, f"the page loaded assets from elsewhere: {foreign}"
            assert not errors, errors
        except BaseException:
            try:  # what the page showed when it failed, for the CI artifacts
                page.screenshot(path=str(ARTIFACTS / "browser-failure.png"), full_page=True)
                (ARTIFACTS / "browser-failure.html").write_text(page.content())
                with httpx.Client(base_url=live.url, timeout=10) as api:
                    ids = [b["id"] for b in api.get("/api/batches", headers=auth("operator")).json()]
                    status = [api.get(f"/api/batches/{i}", headers=auth("operator")).json() for i in ids]
                (ARTIFACTS / "browser-failure-status.json").write_text(json.dumps(status, indent=1))
            except Exception:  # noqa: BLE001
                pass
            raise
        finally:
            browser.close()
