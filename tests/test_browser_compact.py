"""The operator page, in headless Chromium, polls the compact status while a 64-DUT batch runs, and
fetches the rest once, when it changes (issue 40).

The batch is tests/test_web_compact_world.py's: 64 slots late in a sfem-24 batch (step 61 of 72,
thousands of transitions), 12 of them finished with their results and verdicts, 12 faulted,
served by the real daemon and routes. The page shows it in full (every card, the faulted slots, the
verdicts and their trays, the 73-row step list with the running step); then, over several poll
ticks, every request for the batch's status asks for `view=compact` (never the full status), each
answer under 8 KiB, and nothing else is asked for again while nothing changes (each finished
run's result and plot were fetched once). A verdict that
comes to one slot is fetched for that slot alone; the next step brings the step list once; the
station's overload alarm (in the compact view) shows as a banner.
"""

from __future__ import annotations

import time
from urllib.parse import parse_qs, urlsplit

import pytest

from test_web_compact_world import N_SLOTS, STEP_NOW, big_batch, finished_batch, forget
from web_support import CHROMIUM, TOKENS, LiveStation, chromium_page

LIMIT = 8192

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]


class Traffic:
    """Every request the page made for the batch: (monotonic time, path, query, status, body bytes)."""

    def __init__(self, page, bid: int) -> None:
        self.rows: list[tuple[float, str, dict, int, int]] = []
        self.prefix = f"/api/batches/{bid}"
        page.on("requestfinished", self._done)

    def _done(self, req) -> None:
        u = urlsplit(req.url)
        if u.path.startswith(self.prefix) or u.path.startswith("/api/runs/") or u.path == "/api/batches":
            resp = req.response()
            self.rows.append((time.monotonic(), u.path, parse_qs(u.query), resp.status if resp else 0,
                              req.sizes()["responseBodySize"]))

    def since(self, t0: float, path: str | None = None) -> list[tuple[float, str, dict, int, int]]:
        return [r for r in self.rows if r[0] >= t0 and (path is None or r[1] == path)]


def test_the_page_polls_the_compact_view_and_fetches_the_rest_once(tmp_path):
    pytest.importorskip("playwright.sync_api")
    with LiveStation(tmp_path, n_serial=2, n_can=1, speed=600.0, fixture=True) as live:
        bid = big_batch(live, finished_batch(live), 5000, ended=False)
        seq = live.station.batches[bid]
        try:
            with chromium_page(1280, 800, timeout_ms=60_000) as (page, errors):
                traffic = Traffic(page, bid)
                page.goto(live.url + "/")
                page.evaluate(f"() => localStorage.setItem('station.token', {TOKENS['operator']!r})")
                page.goto(live.url + "/")
                # everything the page shows of the batch, from the compact view and the fetched rest
                page.wait_for_function(
                    f"() => document.querySelector('#batch-id').textContent === '{bid}'"
                    f" && document.querySelectorAll('.slot-card[data-state]').length >= {N_SLOTS}"
                    " && document.querySelectorAll('#steps .step').length === 73"
                    " && document.querySelectorAll('.slot-card.has-verdict').length === 24"
                    " && document.querySelectorAll('#trays .tray-slot').length === 24")
                shown = page.evaluate("""() => ({
                    running: document.querySelectorAll('.slot-card[data-state="running"]').length,
                    faulted: [...document.querySelectorAll('#batch-faults .fault-line')].map((e) => e.dataset.slot),
                    runningStep: document.querySelector('#steps .step[data-state="running"]').dataset.index,
                    step: document.querySelector('#batch-step').textContent,
                    counts: document.querySelector('#batch-counts').textContent,
                    prompt: document.querySelector('#prompt-text').textContent,
                    serial: document.querySelector('.slot-card[data-slot="s13"] .serial').textContent,
                    fault: document.querySelector('.slot-card[data-slot="c05"] .reason').textContent,
                    samples: document.querySelector('.slot-card[data-slot="s02"] .samples').textContent,
                    waiting: document.querySelector('.slot-card[data-slot="s02"] .waiting-for').textContent,
                    dots: document.querySelectorAll('.slot-card[data-slot="s02"] .dot.on').length,
                    trace: document.querySelector('#batch-trace-text').textContent,
                })""")
                assert shown["running"] == 40 and len(shown["faulted"]) == 12, shown
                assert shown["runningStep"] == str(STEP_NOW) and shown["step"].startswith(f"{STEP_NOW + 1} / 72"), shown
                assert shown["counts"].startswith("40 running · 12 done · 12 faulted"), shown
                assert "turn the plate to" in shown["prompt"] and "label" in shown["serial"], shown
                assert "link lost" in shown["fault"] and int(shown["samples"]) > 1_000_000, shown
                assert shown["waiting"] and shown["dots"] == min(STEP_NOW, 40), shown
                assert shown["trace"] == "WO WO-24-0815 · part ACC-3DSH-01 rev C · lot L2411-07", shown
                # each finished slot's run (result and plot) once, as it is stored (the plot route
                # answers a burst with 429: the page tries again at its next poll)
                page.wait_for_function("() => [...document.querySelectorAll('.slot-card img.plot-thumb')]"
                                       ".filter((i) => i.complete && i.naturalWidth > 0).length === 24")
                page.screenshot(path=str(tmp_path / "compact-64.png"))

                # several ticks with nothing changed: the compact view only, each answer small
                t0 = time.monotonic()
                page.wait_for_timeout(7000)
                polls = traffic.since(t0, f"/api/batches/{bid}")
                assert len(polls) >= 3, traffic.since(t0)
                assert all(q.get("view") == ["compact"] for _t, _p, q, _s, _n in polls), polls
                assert all(n < LIMIT for *_rest, n in polls), polls
                again = [r for r in traffic.since(t0) if r[1] != f"/api/batches/{bid}"]
                assert again == [], f"asked for again although nothing changed: {again}"
                # and never the full status, since the page opened
                full = [r for r in traffic.rows if r[1] == f"/api/batches/{bid}" and r[2].get("view") != ["compact"]]
                assert full == [], full
                found = [q for _t, p, q, _s, _n in traffic.rows if p == "/api/batches"]  # at start-up: which batch
                assert found and all(q.get("view") == ["compact"] for q in found), found

                # a verdict comes to s05: its fields are fetched for s05 alone, once
                names = [d.slot for d in seq.duts]
                d = seq.duts[names.index("s05")]
                t1 = time.monotonic()
                live.call(lambda: setattr(d, "verdict", {
                    "verdict": "fail", "grade": None, "tray": "reject", "reason": "z TDSF -612 ppm/C, limit -500",
                    "attempt": 1, "limits_name": "LIS3DSH-default", "limits_version": "2", "run_id": d.run_id}))
                page.wait_for_selector('.slot-card[data-slot="s05"].has-verdict[data-verdict="fail"]')
                page.wait_for_selector('#trays .tray-slot[data-slot="s05"][data-verdict="fail"]')
                page.wait_for_timeout(4500)
                fetched = traffic.since(t1, f"/api/batches/{bid}/slots")
                assert [(q.get("slot"), q.get("result")) for _t, _p, q, _s, _n in fetched] == [(["s05"], ["false"])]

                # the next step: the step list once, its new running row
                t2 = time.monotonic()

                def next_step() -> None:
                    t = time.time()
                    seq.history += [(t, "logging", "step_done"), (t, "step_done", "step_setup"),
                                    (t, "step_setup", "logging")]
                    seq.step_index = STEP_NOW + 1

                live.call(next_step)
                page.wait_for_selector(f'#steps .step[data-index="{STEP_NOW + 1}"][data-state="running"]')
                page.wait_for_selector(f'#steps .step[data-index="{STEP_NOW}"][data-state="done"]')
                page.wait_for_timeout(4500)
                assert len(traffic.since(t2, f"/api/batches/{bid}/steps")) == 1, traffic.since(t2)
                assert all(q.get("view") == ["compact"] for _t, _p, q, _s, _n in traffic.since(t2, f"/api/batches/{bid}"))

                # the station cannot follow its boards: the compact view's overload alarm is a banner
                station = live.station
                words = "station overloaded: 4.2 s behind s07 (samples lost meanwhile are the station's, not the part's)"
                real = station.batch_status
                live.call(lambda: setattr(station, "batch_status", lambda b: {
                    **real(b), "overload": {"behind_s": 4.2, "alarm": words, "lost_station": 120,
                                            "lost_by_slot": {"s07": 120}}}))
                try:
                    page.wait_for_function(f"() => !document.querySelector('#overload').classList.contains('hidden')"
                                           f" && document.querySelector('#overload').textContent === {words!r}")
                finally:
                    live.call(lambda: delattr(station, "batch_status"))
                page.wait_for_selector("#overload.hidden", state="attached")
                assert not errors, errors
        finally:
            forget(live, bid)
