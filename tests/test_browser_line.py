"""The operator page through a line's day, in headless Chromium (Debian's package, Playwright) at the
800x480 kiosk and at 1280x800.

1. A batch started the way the line does it: the operator's name required (no fallback, nothing kept
   in localStorage, gone after sign-out); work order, part, revision, lot and the parts' label
   serials typed like a barcode scanner (fill + Enter; Enter never starts a batch); one wrong label
   stops its slot with the reason on its card. While it runs at 800x480: a compact header, the step
   list, the progress bar and a slot card in view. At the end the verdicts are on top without
   scrolling (title flash and a tone); a reload (with no batch id stored) shows the batch again.
   Then a FRESH tab (a new browser context: nothing of the first session) signs in: "New batch" ticks
   every slot (the mismatched one is ready again), "Retest failed" opens the form with only the
   slots that ended error, fail or marginal ticked, their labels empty and the operator's name
   required, the work order, part and lot kept; the right label scanned, the retest runs only those
   slots, each judged on its merit, and the mismatched serial's first real run is attempt 1.
2. A plate turned by hand: each prompt shows a picture of the position (checked against
   contracts/positions.py for all 32 positions), a tone and a title flash (and none when muted);
   "Cannot do it" needs the operator's words and ends the DUTs as error with them.
Screenshots go to artifacts/line-*.png.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import httpx
import pytest

from web_support import CHROMIUM, TOKENS, LiveStation, auth, chromium_page, wait_for

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]

# Counts the tones the page makes (WebAudio oscillators started), and keeps what an old page left
# in localStorage: the page must delete it, not use it.
TONE_SPY = """
window.__tones = 0;
const __start = OscillatorNode.prototype.start;
OscillatorNode.prototype.start = function (...a) { window.__tones += 1; return __start.apply(this, a); };
"""


def shot(page, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"line-{name}.png"))


def watch_csp(page) -> list[str]:
    """The station serves the page with a strict Content-Security-Policy: anything it refuses (an
    inline style in generated markup, a foreign host) shows only on the console."""
    refused: list[str] = []
    page.on("console", lambda m: refused.append(m.text) if "Content Security Policy" in m.text else None)
    return refused


def sign_in(page, url: str) -> None:
    page.goto(url + "/")
    page.fill("#token", TOKENS["operator"])
    page.click("#save-token")
    page.wait_for_selector("#whoami #sign-out")


def status(live, batch_id: int) -> dict:
    return httpx.get(f"{live.url}/api/batches/{batch_id}", headers=auth("operator"), timeout=10).json()


def batches(live) -> list[dict]:
    return httpx.get(f"{live.url}/api/batches", headers=auth("operator"), timeout=10).json()


def clock_s(text: str) -> int:
    """'1:02:03' or '2:03' (the page's clock) in seconds."""
    s = 0
    for part in text.split(":"):
        s = s * 60 + int(part)
    return s


def focused(page) -> str:
    return page.evaluate("() => document.activeElement.id || document.activeElement.dataset.slot || ''")


def storage(page) -> dict:
    return page.evaluate("() => ({local: localStorage.getItem('station.operator'),"
                         " session: sessionStorage.getItem('station.operator'),"
                         " field: document.querySelector('#operator').value})")


IN_VIEWPORT_JS = """s => { const e = document.querySelector(s); if (!e) return false;
        const r = e.getBoundingClientRect();
        return r.height > 0 && r.top >= 0 && r.bottom <= innerHeight && r.left >= 0 && r.right <= innerWidth; }"""


def in_viewport(page, selector: str) -> bool:
    return page.evaluate(IN_VIEWPORT_JS, selector)


WHERE_JS = """s => { const e = document.querySelector(s); const r = e && e.getBoundingClientRect();
        return {selector: s, rect: r && [r.left, r.top, r.right, r.bottom], scrollY, innerWidth, innerHeight}; }"""


def comes_into_viewport(page, selector: str, timeout_ms: int = 5000) -> bool:
    """After a resize the page lays out again (and may re-render on the next status): wait for it.
    Fails naming where the element is and where the window is."""
    try:
        page.wait_for_function(IN_VIEWPORT_JS, arg=selector, timeout=timeout_ms)
        return True
    except Exception:  # noqa: BLE001 - the assert below says where the element is
        where = page.evaluate(WHERE_JS, selector)
        assert in_viewport(page, selector), where
        return True


def test_scanned_batch_labels_steps_end_reload_and_retest(tmp_path):
    pytest.importorskip("playwright.sync_api")
    with LiveStation(tmp_path, n_serial=3, n_can=1, speed=300.0, fixture=True) as live, \
            chromium_page(800, 480) as (page, errors):
        foreign = []
        page.on("request", lambda r: None if r.url.startswith((live.url, "blob:", "data:")) else foreign.append(r.url))
        page.add_init_script(TONE_SPY)
        refused = watch_csp(page)
        # what the old page left for the next person on a shared kiosk
        page.add_init_script("if (!sessionStorage.getItem('seeded')) { localStorage.setItem('station.operator', 'Previous Person');"
                             " sessionStorage.setItem('seeded', '1'); }")
        try:
            sign_in(page, live.url)
            page.wait_for_selector("#slot-picks input.label-serial[data-slot='c1']", state="attached")
            assert storage(page) == {"local": None, "session": None, "field": ""}  # deleted, never used
            serials = {s["slot"]: s["serial"] for s in httpx.get(f"{live.url}/api/slots", headers=auth("operator")).json()}

            # no name, no batch: a clear message, nothing sent
            page.click("#start")
            assert "Operator name required" in page.inner_text("#message")
            assert page.get_attribute("#operator", "aria-invalid") == "true"
            assert batches(live) == []

            # typed like a scanner: each code ends with Enter, which moves to the next field
            page.select_option("#profile", "fast-thermal")
            page.fill("#operator", "Ana Lopez")
            page.press("#operator", "Enter")
            trace = {"work-order": "WO-24-0815", "part-number": "ACC-3DSH-01", "part-revision": "C", "lot": "L2411-07"}
            for field, code in trace.items():
                assert focused(page) == field
                page.keyboard.type(code)
                page.keyboard.press("Enter")
            labels = {"s1": serials["s1"], "s2": serials["s2"], "s3": "SIM9999"}  # s3's label is another part's
            for slot in ["s1", "s2", "s3"]:
                assert focused(page) == slot
                page.keyboard.type(labels[slot])
                page.keyboard.press("Enter")
            assert focused(page) == "c1"  # no label scanned for c1
            page.keyboard.press("Enter")
            assert focused(page) == "start"  # the last Enter lands on Start and does not press it
            assert batches(live) == []
            page.evaluate("() => document.querySelector('#slot-picks').scrollIntoView({block: 'end'})")
            shot(page, "start-scanned-800x480")
            page.set_viewport_size({"width": 1280, "height": 800})
            page.evaluate("() => window.scrollTo(0, 0)")
            shot(page, "start-scanned-1280x800")
            page.set_viewport_size({"width": 800, "height": 480})
            page.click("#start")

            page.wait_for_selector("#batch-panel:not(.hidden)")
            batch_id = int(page.inner_text("#batch-id"))
            st = status(live, batch_id)
            assert st["operator"] == "Ana Lopez"
            assert (st["work_order"], st["part_number"], st["part_revision"], st["lot"]) == tuple(trace.values())
            assert st["labels"] == labels
            assert storage(page) == {"local": None, "session": "Ana Lopez", "field": "Ana Lopez"}

            # running at 800x480: step list, progress bar, a compact header, a slot card in view
            page.wait_for_selector("#steps .step[data-state='running']")
            page.wait_for_function("() => parseFloat(document.querySelector('#progress-bar').style.width) > 0")
            page.evaluate("() => window.scrollTo(0, 0)")
            header_px = page.evaluate("() => document.querySelector('header.top').getBoundingClientRect().height")
            card_top_px = page.evaluate("() => document.querySelector('.slot-card').getBoundingClientRect().top")
            (ARTIFACTS / "line-measurements.json").write_text(json.dumps(
                {"viewport": "800x480", "state": "running", "header_px": header_px, "first_slot_card_top_px": card_top_px}))
            assert header_px <= 60, header_px
            assert card_top_px + 60 <= 480, card_top_px  # at least its name and serial show
            assert page.evaluate("() => document.documentElement.scrollWidth") <= 800
            # each chip's parts by their own elements (innerText of a chip being re-laid out can come
            # back without its spaces: "1P ambient0:00 / ~0:03")
            texts = page.locator("#steps .step").all_text_contents()
            names = page.locator("#steps .step .step-name").all_text_contents()
            assert [n.split()[0] for n in names[:1]] == ["P"], texts  # "1 P ambient 0:01 / ~0:04"
            assert len(texts) == len(names) == len(st["steps"])
            lefts, progress = [], []
            deadline = time.monotonic() + 3
            while time.monotonic() < deadline and status(live, batch_id)["state"] == "running":
                lefts.append(page.evaluate("() => document.querySelector('#progress-text').textContent"))
                progress.append(float(page.evaluate("() => parseFloat(document.querySelector('#progress-bar').style.width)")))
                time.sleep(0.25)
            shot(page, "running-800x480")
            assert progress == sorted(progress), progress  # the bar never goes back
            left_s = [clock_s(m.group(1)) for t in lefts if (m := re.search(r"(\d+:\d\d(?::\d\d)?) left", t))]
            assert left_s and left_s == sorted(left_s, reverse=True), lefts  # the time left only decreases

            # the wrong label stops its slot; the reason shows on its card
            s3 = page.locator('.slot-card[data-slot="s3"] .fault')
            s3.wait_for()
            wait_for(lambda: status(live, batch_id)["slots"][2]["error"], 10, what="s3's fault")
            api_s3 = {s["slot"]: s for s in status(live, batch_id)["slots"]}["s3"]
            assert api_s3["state"] == "faulted" and api_s3["label_serial"] == "SIM9999"
            assert "label serial 'SIM9999' does not match the board's own serial" in api_s3["error"]
            assert api_s3["error"] in s3.inner_text()
            page.evaluate("() => document.querySelector('.slot-card[data-slot=\"s3\"]').scrollIntoView({block: 'start'})")
            shot(page, "label-mismatch-800x480")
            page.evaluate("() => window.scrollTo(0, 0)")

            # the end: verdicts and sorting on top, visible without scrolling; a tone and a title flash
            tones_before_end = page.evaluate("() => window.__tones")
            page.wait_for_function("() => document.querySelector('#batch-state').textContent === 'finished'", timeout=90_000)
            page.wait_for_function("() => document.title === '● Batch ended'")
            assert page.evaluate("() => window.__tones") > tones_before_end
            st = status(live, batch_id)
            page.wait_for_function(f"() => document.querySelectorAll('#trays .tray-slot').length === {len(st['sorting'])}")
            assert page.evaluate("() => window.scrollY") == 0
            for e in st["sorting"]:
                assert in_viewport(page, f'#trays .tray-slot[data-slot="{e["slot"]}"]'), e["slot"]
                row = page.locator(f'.tray-row:has(.tray-slot[data-slot="{e["slot"]}"])')
                assert row.locator(".tray-verdict").inner_text() == e["verdict"].upper()
            assert page.is_hidden("#start-panel") and in_viewport(page, "#new-batch")
            failed = sorted(s["slot"] for s in st["slots"] if s["verdict"] in ("fail", "error"))
            assert "s3" in failed and in_viewport(page, "#retest")
            shot(page, "end-800x480")
            page.set_viewport_size({"width": 1280, "height": 800})
            assert comes_into_viewport(page, "#sorting") and comes_into_viewport(page, "#retest")
            shot(page, "end-1280x800")

            # a reload, with no batch id left in the browser: the newest batch from the station
            page.set_viewport_size({"width": 800, "height": 480})
            page.evaluate("() => localStorage.removeItem('station.batch')")
            page.reload()
            page.wait_for_function(f"() => document.querySelector('#batch-id').textContent === '{batch_id}'")
            page.wait_for_function("() => document.querySelector('#batch-state').textContent === 'finished'")
            page.wait_for_function(f"() => document.querySelectorAll('#trays .tray-slot').length === {len(st['sorting'])}")
            assert in_viewport(page, "#sorting") and page.is_hidden("#start-panel")
            assert "WO WO-24-0815" in page.inner_text("#batch-trace-text")
            assert storage(page)["session"] == "Ana Lopez"  # the same person, same tab
            shot(page, "reload-800x480")

            fresh_retest(page, live, batch_id, st, serials, trace)

            # sign-out: the name is gone from the page and the browser
            page.click("#sign-out")
            page.wait_for_selector("#auth:not(.hidden)")
            assert storage(page) == {"local": None, "session": None, "field": ""}
            sign_in(page, live.url)
            assert storage(page) == {"local": None, "session": None, "field": ""}
            assert not foreign, foreign
            assert not errors, errors
            assert not refused, refused
        except BaseException:
            shot(page, "failure-1")
            raise


def fresh_retest(page, live, batch_id: int, st: dict, serials: dict, trace: dict) -> None:
    """"Retest failed" in a fresh tab mends the label mismatch of s3 (see the module's doc)."""
    def all_judged(bid: int):
        x = status(live, bid)
        return x if x["state"] in ("finished", "failed", "aborted") and all(s["verdict"] for s in x["slots"]) else None

    st = wait_for(lambda: all_judged(batch_id), 30, what="every verdict of the first batch")
    again = [s["slot"] for s in st["slots"] if s["verdict"] in ("error", "fail", "marginal")]  # the station's order
    assert "s3" in again
    ctx = page.context.browser.new_context(viewport={"width": 800, "height": 480})
    fresh = ctx.new_page()
    errors: list[str] = []
    fresh.on("pageerror", lambda e: errors.append(f"{e} at {getattr(e, 'stack', '')}"))
    fresh.set_default_timeout(20_000)
    refused = watch_csp(fresh)
    checked = "() => [...document.querySelectorAll('#slot-picks input[type=checkbox]:checked')].map(i => i.value).sort()"
    try:
        sign_in(fresh, live.url)
        fresh.wait_for_function(f"() => document.querySelector('#batch-id').textContent === '{batch_id}'")
        fresh.wait_for_function("() => document.querySelector('#batch-state').textContent === 'finished'")
        assert storage(fresh) == {"local": None, "session": None, "field": ""}  # nobody signed in here yet
        # the slot whose label was wrong is ready again: a new batch's form ticks every slot
        fresh.click("#new-batch")
        fresh.wait_for_selector("#start-panel:not(.hidden)")
        fresh.wait_for_function(f"() => ({checked})().length === {len(st['slots'])}")
        assert fresh.is_hidden("#start-mode") and fresh.inner_text("#start") == "Start batch"
        fresh.click("#start-cancel")
        fresh.wait_for_selector("#start-panel", state="hidden")

        # Retest failed: only those slots ticked (the others cannot be), labels empty, trace kept
        fresh.click("#retest")
        fresh.wait_for_selector("#start-panel:not(.hidden)")
        fresh.wait_for_function("() => !document.querySelector('#start-mode').classList.contains('hidden')")
        assert fresh.evaluate(checked) == sorted(again)
        assert sorted(fresh.evaluate("() => [...document.querySelectorAll('#slot-picks input[type=checkbox]:not(:disabled)')]"
                                     ".map(i => i.value)")) == sorted(again)
        labels = fresh.evaluate("() => Object.fromEntries([...document.querySelectorAll('#slot-picks input.label-serial:not(:disabled)')]"
                                ".map(i => [i.dataset.slot, i.value]))")
        assert labels == {k: "" for k in again}, labels
        assert f"Retest of batch {batch_id}: {', '.join(again)}" in fresh.inner_text("#start-mode")
        assert fresh.inner_text("#start") == "Start retest"
        assert fresh.input_value("#profile") == "fast-thermal" and fresh.is_disabled("#profile")
        for field, code in trace.items():
            assert fresh.input_value(f"#{field}") == code and fresh.is_disabled(f"#{field}")
        assert focused(fresh) == "operator"
        shot(fresh, "retest-form-800x480")
        fresh.click("#start")  # no name: nothing is started
        assert "Operator name required to retest" in fresh.inner_text("#message")
        assert [b["id"] for b in batches(live)] == [batch_id]

        # scanned like a scanner: the name, then each retested part's label (the right one now)
        fresh.fill("#operator", "Bea Ruiz")
        fresh.press("#operator", "Enter")
        for slot in again:
            assert focused(fresh) == slot
            fresh.keyboard.type(serials[slot])
            fresh.keyboard.press("Enter")
        assert focused(fresh) == "start"
        assert [b["id"] for b in batches(live)] == [batch_id]  # Enter never starts it
        fresh.click("#start")
        fresh.wait_for_function(f"() => Number(document.querySelector('#batch-id').textContent) > {batch_id}")
        retest_id = int(fresh.inner_text("#batch-id"))
        rt = status(live, retest_id)
        assert [s["slot"] for s in rt["slots"]] == again
        assert rt["labels"] == {k: serials[k] for k in again} and rt["operator"] == "Bea Ruiz"
        assert (rt["work_order"], rt["part_number"], rt["part_revision"], rt["lot"]) == tuple(trace.values())
        assert rt["profile"] == "fast-thermal"
        assert fresh.is_hidden("#start-panel")

        end = wait_for(lambda: all_judged(retest_id), 90, what="the retest's end and verdicts")
        assert end["state"] == "finished", end.get("error")
        s3 = next(s for s in end["slots"] if s["slot"] == "s3")
        assert s3["state"] == "done" and s3["verdict"] in ("pass", "marginal", "fail"), s3  # on its merit
        assert s3["attempt"] == 1 and s3["samples"] > 0
        card = fresh.locator('.slot-card[data-slot="s3"] .verdict-word')
        card.wait_for()
        fresh.wait_for_function(f"() => document.querySelector('.slot-card[data-slot=\"s3\"] .verdict-word')"
                                f".textContent === '{s3['verdict'].upper()}'")
        shot(fresh, "retest-end-800x480")

        # the serial's attempts: the mismatched run is in its history but is no attempt
        live.flush_db()
        dut = httpx.get(f"{live.url}/api/duts/{serials['s3']}", headers=auth("operator"), timeout=10).json()
        assert (dut["attempts"], dut["n_runs"], dut["attempt"], dut["verdict"]) == (1, 2, 1, s3["verdict"]), dut
        runs = httpx.get(f"{live.url}/api/duts/{serials['s3']}/runs", headers=auth("operator"), timeout=10).json()
        assert [(r["batch_id"], r["attempt"]) for r in runs] == [(retest_id, 1), (batch_id, 0)]
        first = {s["slot"]: s["verdict"] for s in st["slots"] if s["slot"] != "s3"}
        first["s3"] = s3["verdict"]  # its first run that tested the part
        final = {**first, **{s["slot"]: s["verdict"] for s in end["slots"] if s["verdict"] != "error"}}
        y = httpx.get(f"{live.url}/api/yield", headers=auth("mes"), timeout=10).json()
        assert y["duts"] == len(st["slots"]) and y["first_pass"] == sum(v == "pass" for v in first.values()), (y, first)
        assert y["final_pass"] == sum(v == "pass" for v in final.values()), (y, final)
        assert not errors, errors
        assert not refused, refused
    except BaseException:
        shot(fresh, "failure-retest")
        raise
    finally:
        ctx.close()


def test_prompt_picture_mute_and_cannot_do_it(tmp_path):
    pytest.importorskip("playwright.sync_api")
    from contracts.positions import GRAVITY_DIRECTIONS, POSITION_NAMES

    with LiveStation(tmp_path, n_serial=2, n_can=1, speed=300.0, fixture=False, operator_hands=True) as live, \
            chromium_page(1280, 800) as (page, errors):
        page.add_init_script(TONE_SPY)
        refused = watch_csp(page)
        try:
            sign_in(page, live.url)
            page.evaluate("() => localStorage.removeItem('station.mute')")
            page.select_option("#profile", "fast-thermal")
            page.fill("#operator", "Ben")
            page.click("#start")

            # the first prompt: the picture of P, the answers, a tone and the title flash
            page.wait_for_selector("#prompt-banner:not(.hidden) svg.orientation[data-position='P']")
            batch_id = int(page.inner_text("#batch-id"))
            prompt = wait_for(lambda: status(live, batch_id)["prompt"], 10, what="the prompt in the status")
            assert prompt["position_name"] == "P"
            shown = [float(v) for v in page.get_attribute("svg.orientation", "data-direction").split(",")]
            assert shown == pytest.approx(prompt["direction"], abs=0.006)
            assert page.inner_text("#prompt-words") == "P: x up · y up · z up"
            assert page.is_visible("#prompt-confirm") and page.is_visible("#prompt-cannot")
            page.wait_for_function("() => document.title === '● Prompt waiting'")
            page.wait_for_function("() => window.__tones > 0")
            shot(page, "prompt-P-1280x800")
            page.set_viewport_size({"width": 800, "height": 480})
            page.wait_for_timeout(200)
            assert in_viewport(page, "#prompt-picture svg") and in_viewport(page, "#prompt-cannot")
            assert page.evaluate("() => document.documentElement.scrollWidth") <= 800
            shot(page, "prompt-P-800x480")
            page.set_viewport_size({"width": 1280, "height": 800})

            # muted (a station preference, kept in localStorage): the next prompt flashes but is silent
            page.click("#mute")
            assert page.evaluate("() => localStorage.getItem('station.mute')") == "1"
            tones = page.evaluate("() => window.__tones")
            page.click("#prompt-confirm")
            page.wait_for_selector("#prompt-banner:not(.hidden) svg.orientation[data-position='N']", timeout=60_000)
            assert page.inner_text("#prompt-words") == "N: x down · y down · z down"
            page.wait_for_function("() => document.title === '● Prompt waiting'")
            page.wait_for_timeout(300)
            assert page.evaluate("() => window.__tones") == tones
            page.click("#mute")
            assert page.evaluate("() => localStorage.getItem('station.mute')") is None

            # "Cannot do it": words required; then every DUT on the plate ends as error with them
            page.click("#prompt-cannot")
            page.click("#prompt-cannot-send")
            assert "Say why" in page.inner_text("#prompt-cannot-msg")
            assert status(live, batch_id)["prompt"] is not None  # nothing was sent
            words = "plate jammed against the lamp bracket"
            page.fill("#prompt-note", words)
            shot(page, "prompt-cannot-1280x800")
            page.click("#prompt-cannot-send")
            page.wait_for_function("() => document.querySelector('#batch-state').textContent === 'failed'", timeout=30_000)
            def judged():
                st = status(live, batch_id)
                return st if all(x["verdict"] for x in st["slots"]) else None

            st = wait_for(judged, 30, what="verdicts after 'cannot'")
            for s in st["slots"]:
                assert s["verdict"] == "error" and words in (s["reason"] or s["error"]), s
                card = page.locator(f'.slot-card[data-slot="{s["slot"]}"]')
                card.locator(".verdict-word").wait_for()
                assert card.locator(".verdict-word").inner_text() == "ERROR"
                assert words in card.inner_text()
            assert words in st["error"] and words in page.inner_text("#batch-error")
            assert page.is_hidden("#prompt-banner")
            shot(page, "cannot-end-1280x800")
            # the audit names the person at the page (X-Operator), not only the kiosk's token
            audit = httpx.get(f"{live.url}/api/audit", headers=auth("admin"), timeout=10).json()
            answers = [a for a in audit if a["action"] == "prompt.answer" and a["detail"].get("answer") == "cannot"]
            assert answers and answers[0]["actor"].startswith("Ben (token ") and answers[0]["detail"]["note"] == words

            # every position's picture (by name, no direction given: the page's own table) against
            # contracts/positions.py: an axis the board must read up points up on the screen
            names = list(POSITION_NAMES)
            pics = page.evaluate("""names => names.map((n) => {
                const box = document.createElement('div'); box.className = 'gallery-item';
                box.innerHTML = promptPicture({position_name: n}).svg; document.body.append(box);
                const svg = box.querySelector('svg');
                const axes = {};
                for (const g of svg.querySelectorAll('g.axis')) {
                  const l = g.querySelector('line');
                  axes[g.dataset.axis] = Number(l.getAttribute('y1')) - Number(l.getAttribute('y2'));  // > 0: drawn upwards
                }
                return {name: svg.dataset.position, direction: svg.dataset.direction.split(',').map(Number), axes};
            })""", names)
            for pic, truth in zip(pics, GRAVITY_DIRECTIONS):
                assert pic["direction"] == pytest.approx(list(truth), abs=0.006), pic["name"]
                for i, ax in enumerate("xyz"):
                    if abs(truth[i]) > 0.2:
                        assert (pic["axes"][ax] > 0) == (truth[i] > 0), (pic["name"], ax, pic["axes"])
            assert not errors, errors  # the page's own errors, before the gallery below takes its DOM away
            page.evaluate("""() => { document.body.replaceChildren(...document.querySelectorAll('.gallery-item'));
                document.body.style.cssText = 'display:flex;flex-wrap:wrap;gap:4px;background:#000';
                for (const s of document.querySelectorAll('.gallery-item svg')) s.style.cssText = 'width:200px;height:172px'; }""")
            page.screenshot(path=str(ARTIFACTS / "line-orientations.png"), full_page=True)
            assert not refused, refused
        except BaseException:
            shot(page, "failure-2")
            raise
