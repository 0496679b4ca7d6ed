"""The operator page's end view and running kiosk for real people (issue 34), in headless Chromium.

1. The end view at the 800x480 kiosk and at 1280x800, with the full trace header (work order, part,
   revision, lot), for ended batches served by the real app from real database rows
   (tests/end_view_support.py: verdicts by the station's own final_verdict, faults in the daemon's
   words): 12 slots of mixed outcomes (pass A/B, marginal, fail, a lost link, a label mismatch), 11
   slots of which none passed, 12 exceptions of six kinds in a failed batch (the most the kiosk
   must hold), and 4 that all passed. Measured from the DOM: every slot's verdict
   and tray in the viewport without scrolling, the trace header on one line, the trays exceptions
   first (error, fail, marginal/hold, then pass), each exception with its reason; the state chip,
   the outcome chip and the bar coloured by the outcome (never green when nothing passed: red, in
   words "0 of 11 pass"), green when all passed.
2. A running batch on the kiosk (a live simulated station) names its faulted slot ("1 faulted: s3")
   with its reason on a line of its own; a tap on it shows the slot's card with the whole reason.

Screenshots: artifacts/end-view-{mixed,none-passed,twelve-exceptions}-{800x480,1280x800}.png,
artifacts/end-view-running-faulted-800x480.png.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import pytest
from fastapi import HTTPException

from end_view_support import Slot, mixed_slots, nothing_passed_slots, twelve_exceptions_slots, write_ended_batch
from web_support import CHROMIUM, TOKENS, IdleStation, LiveStation, auth, chromium_page, serve_in_thread, wait_for

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"
TOKEN = "operator-token-end-view-01"
TRACE_TEXT = "WO WO-24-0815 · part ACC-3DSH-01 rev C · lot L2411-07"
RANK = {"error": 0, "fail": 1, "marginal": 2, "pass": 3}
GREEN = "rgb(47, 191, 113)"  # var(--ok)

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]


class StoredOnly(IdleStation):
    """A daemon that holds no batch: the page gets each ended batch from the database."""

    def batch_status(self, batch_id):
        raise HTTPException(status_code=404, detail=f"batch {batch_id} not found")


# Everything the assertions need, measured in one task (the page re-renders on every poll).
MEASURE_JS = """() => {
  const inView = (e) => { if (!e) return false; const r = e.getBoundingClientRect();
    return r.height > 0 && r.top >= 0 && r.bottom <= innerHeight && r.left >= 0 && r.right <= innerWidth; };
  const bg = (e) => e ? getComputedStyle(e).backgroundColor : null;
  const trace = document.querySelector('#batch-trace-text');
  const lh = parseFloat(getComputedStyle(trace).lineHeight);
  return {
    scrollY, scrollWidth: document.documentElement.scrollWidth, innerWidth,
    rows: [...document.querySelectorAll('#trays .tray-row')].map((row) => ({
      tray: row.dataset.tray, verdict: row.dataset.verdict, word: row.querySelector('.tray-verdict').textContent,
      wordInView: inView(row.querySelector('.tray-verdict')), nameInView: inView(row.querySelector('.tray-name')),
      slots: [...row.querySelectorAll('.tray-slot')].map((s) => ({slot: s.dataset.slot, verdict: s.dataset.verdict,
        inView: inView(s), why: (s.querySelector('.tray-why') || {}).textContent || '', title: s.title})),
    })),
    trace: trace.textContent, traceInView: inView(trace), traceLines: trace.getBoundingClientRect().height / lh,
    state: document.querySelector('#batch-state').textContent, stateBg: bg(document.querySelector('#batch-state')),
    stateInView: inView(document.querySelector('#batch-state')),
    outcome: document.querySelector('#batch-outcome').textContent,
    outcomeKind: document.querySelector('#batch-outcome').dataset.outcome,
    outcomeBg: bg(document.querySelector('#batch-outcome')), outcomeInView: inView(document.querySelector('#batch-outcome')),
    progressText: document.querySelector('#progress-text').textContent,
    segments: [...document.querySelectorAll('#progress-bar .outcome-seg')].map((s) => ({verdict: s.dataset.verdict,
      bg: bg(s), width: s.getBoundingClientRect().width})),
    barWidth: document.querySelector('#progress-bar').getBoundingClientRect().width,
    buttonsInView: ['#retest', '#new-batch'].filter((s) => !document.querySelector(s).classList.contains('hidden'))
      .map((s) => [s, inView(document.querySelector(s))]),
  };
}"""


def _show(page, url: str, batch: int, n_slots: int) -> dict:
    page.evaluate(f"() => {{ localStorage.setItem('station.token', {TOKEN!r}); localStorage.setItem('station.batch', '{batch}'); }}")
    page.goto(url + "/")
    page.wait_for_function(f"() => document.querySelector('#batch-id').textContent === '{batch}'"
                           f" && document.querySelectorAll('#trays .tray-slot').length === {n_slots}"
                           " && document.querySelector('#batch-outcome').textContent !== ''")
    page.evaluate("() => window.scrollTo(0, 0)")
    time.sleep(0.9)  # the layout settles and the bar has grown to its width (a 0.6 s transition)
    return page.evaluate(MEASURE_JS)


def _check_end_view(m: dict, expect: dict, size: str) -> None:
    """Every slot's verdict in view, exceptions first, the trace on one line (see the module doc)."""
    width = int(size.split("x")[0])
    assert m["scrollY"] == 0 and m["scrollWidth"] <= width, (size, m["scrollY"], m["scrollWidth"])
    shown = {s["slot"]: (s, row) for row in m["rows"] for s in row["slots"]}
    assert set(shown) == set(expect), (size, sorted(shown), sorted(expect))
    for slot, e in expect.items():
        s, row = shown[slot]
        assert s["inView"], (size, slot, "slot not in the viewport")
        assert row["wordInView"] and row["nameInView"], (size, slot, row["tray"], "its verdict/tray not in view")
        assert s["verdict"] == row["verdict"] == e["verdict"] and row["word"] == e["verdict"].upper(), (size, slot)
        assert row["tray"] == e["tray"], (size, slot, row["tray"], e["tray"])
        if e["verdict"] != "pass":  # an exception says why on the kiosk; the whole reason is its title (tap/hover)
            assert s["why"] and e["reason"] in s["title"], (size, slot, s)
    ranks = [RANK[r["verdict"]] for r in m["rows"]]
    assert ranks == sorted(ranks), (size, [r["verdict"] for r in m["rows"]])  # error, fail, marginal, then pass
    assert m["trace"] == TRACE_TEXT and m["traceInView"], (size, m["trace"])
    assert m["traceLines"] < 1.5, (size, "the trace header wraps", m["traceLines"])
    assert m["stateInView"] and m["outcomeInView"], size
    assert all(ok for _sel, ok in m["buttonsInView"]), (size, m["buttonsInView"])


def test_end_view_every_verdict_in_view_exceptions_first_outcome_coloured(tmp_path):
    pytest.importorskip("playwright.sync_api")
    from db import Database
    from web.app import create_app
    from web.auth import TokenStore
    from web.db_repo import DbRepository

    ARTIFACTS.mkdir(exist_ok=True)
    db = Database(f"sqlite:///{tmp_path / 'end-view.db'}", station="line-3")
    db.upgrade()
    mixed = write_ended_batch(db, mixed_slots())
    none = write_ended_batch(db, nothing_passed_slots(), operator="Ben")
    good = write_ended_batch(db, [Slot(f"s{i:02d}", "pass A", serial=f"GOOD{i:04d}") for i in range(1, 5)])
    # the most the kiosk must hold: 12 exceptions, six kinds of error, a failed batch with its error line
    worst = write_ended_batch(db, twelve_exceptions_slots(), state="failed",
                              reason="Ana (token line-3 kiosk) could not turn the plate to N: plate jammed against the "
                                     "lamp bracket")
    app = create_app(StoredOnly(db), repo=DbRepository(db), outbox=False,
                     tokens=TokenStore([(TOKEN, "operator", "line-3 kiosk")]))
    url, stop = serve_in_thread(app)
    try:
        with chromium_page(800, 480) as (page, errors):
            page.goto(url + "/")
            for name, batch in (("mixed", mixed), ("none-passed", none), ("twelve-exceptions", worst)):
                for w, h in ((800, 480), (1280, 800)):
                    page.set_viewport_size({"width": w, "height": h})
                    m = _show(page, url, batch["batch"], len(batch["slots"]))
                    page.screenshot(path=str(ARTIFACTS / f"end-view-{name}-{w}x{h}.png"))
                    _check_end_view(m, batch["slots"], f"{w}x{h}")
                    judged = len(batch["slots"])
                    n_pass = sum(e["verdict"] == "pass" for e in batch["slots"].values())
                    state = "failed" if batch is worst else "finished"
                    assert m["state"] == state
                    assert m["outcome"] == f"{n_pass} of {judged} pass", m["outcome"]
                    assert f"{state} · {n_pass} of {judged} pass" in m["progressText"], m["progressText"]
                    # the bar's fill split by verdict, each part as wide as its share
                    counts = {v: sum(e["verdict"] == v for e in batch["slots"].values()) for v in RANK}
                    assert {s["verdict"] for s in m["segments"]} == {v for v, n in counts.items() if n}
                    for s in m["segments"]:
                        assert s["width"] == pytest.approx(m["barWidth"] * counts[s["verdict"]] / judged, abs=6)
                    if n_pass == 0:  # nothing passed: red, never green, anywhere
                        assert m["outcomeKind"] == "none"
                        assert GREEN not in (m["stateBg"], m["outcomeBg"]), (m["stateBg"], m["outcomeBg"])
                        assert all(s["bg"] != GREEN for s in m["segments"]), m["segments"]
                        assert m["stateBg"] == m["outcomeBg"] == "rgb(255, 77, 77)"  # var(--bad)
                    else:  # some passed, not all: amber, and only the pass part of the bar is green
                        assert m["outcomeKind"] == "some" and GREEN not in (m["stateBg"], m["outcomeBg"])
                        assert [s["verdict"] for s in m["segments"] if s["bg"] == GREEN] == ["pass"]
            # the mixed batch's exceptions in words: the label mismatch short, the link left out
            m = _show(page, url, mixed["batch"], len(mixed["slots"]))
            why = {s["slot"]: s["why"] for r in m["rows"] for s in r["slots"]}
            assert why["s03"] == "label SIM9999 ≠ board SIM0003"
            assert why["s08"].startswith("link lost: ") and "/dev/pts/7:" not in why["s08"][:12]
            assert why["s06"] == "z TDSF -612 ppm/C, limit -500"
            assert [r["tray"] for r in m["rows"]] == ["retest", "reject", "hold (review / retest)", "grade A", "grade B"]
            m = _show(page, url, worst["batch"], len(worst["slots"]))
            why = {s["slot"]: s["why"] for r in m["rows"] for s in r["slots"]}
            assert why["s05"].startswith("plate never arrived at N: ")  # the step's name left out
            assert why["s06"] == "could not turn the plate to N: plate jammed against the lamp bracket"
            # all passed: green, in words
            m = _show(page, url, good["batch"], 4)
            assert (m["outcome"], m["outcomeKind"], m["stateBg"], m["outcomeBg"]) == ("all 4 pass", "all", GREEN, GREEN)
            assert errors == [], errors
    finally:
        stop()
        db.dispose()


def test_running_kiosk_names_the_faulted_slot_and_its_reason(tmp_path):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    # x60: the batch runs for about a minute and a half, so the page is still its running view here
    with LiveStation(tmp_path, n_serial=4, n_can=0, speed=60.0, fixture=True) as live, \
            chromium_page(800, 480) as (page, errors):
        trace = {"work_order": "WO-24-0815", "part_number": "ACC-3DSH-01", "part_revision": "C", "lot": "L2411-07"}
        r = httpx.post(f"{live.url}/api/batches", headers=auth("operator"), timeout=30, json={
            "profile": "fast-thermal", "slots": ["s1", "s2", "s3", "s4"], "operator": "Ana", **trace,
            "labels": {"s3": "SIM9999"}})  # s3 holds another part than its label says: stopped at connect
        assert r.status_code == 201, r.text
        batch_id = r.json()["id"]
        page.add_init_script(f"localStorage.setItem('station.token', {TOKENS['operator']!r});")
        page.goto(live.url + "/")
        try:
            page.wait_for_selector("#batch-counts .fault-slot[data-slot='s3']", timeout=30_000)
            page.wait_for_selector("#batch-faults .fault-line[data-slot='s3']")
            st = httpx.get(f"{live.url}/api/batches/{batch_id}", headers=auth("operator"), timeout=10).json()
            assert st["state"] in ("running", "paused"), st["state"]  # still running: the kiosk's running view
            reason = {s["slot"]: s for s in st["slots"]}["s3"]["error"]
            assert "label serial 'SIM9999' does not match the board's own serial" in reason
            counts = page.inner_text("#batch-counts")
            assert re.fullmatch(r"\d+ running · \d+ done · 1 faulted: s3", counts), counts
            m = page.evaluate("""() => { const e = document.querySelector('#batch-faults .fault-line[data-slot="s3"]');
                const r = e.getBoundingClientRect();
                return {text: e.textContent, title: e.title, inView: r.top >= 0 && r.bottom <= innerHeight && r.right <= innerWidth,
                        height: r.height}; }""")
            assert m["inView"] and m["height"] >= 32, m  # on the first screen, big enough to tap
            assert m["text"] == "s3 label SIM9999 ≠ board SIM0003" and m["title"] == reason, m
            page.evaluate("() => window.scrollTo(0, 0)")
            page.screenshot(path=str(ARTIFACTS / "end-view-running-faulted-800x480.png"))
            # a tap on it shows s3's card, with the whole reason
            page.click("#batch-faults .fault-line[data-slot='s3']")
            card = '.slot-card[data-slot="s3"]'
            page.wait_for_function("""(s) => { const r = document.querySelector(s).getBoundingClientRect();
                return r.top > -10 && r.top < innerHeight / 3; }""", arg=card)  # scrolled up to the top of the screen
            assert reason in page.inner_text(f"{card} .fault")
            page.wait_for_timeout(700)  # the smooth scroll ends
            page.screenshot(path=str(ARTIFACTS / "end-view-running-faulted-card-800x480.png"))
            assert errors == [], errors
        except BaseException:
            page.screenshot(path=str(ARTIFACTS / "end-view-running-failure.png"))
            raise
        finally:
            httpx.post(f"{live.url}/api/batches/{batch_id}/abort", headers=auth("operator"), timeout=10)
            wait_for(lambda: httpx.get(f"{live.url}/api/batches/{batch_id}", headers=auth("operator"),
                                       timeout=10).json()["state"] != "running", 30, what="the abort")
