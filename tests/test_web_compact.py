"""The operator page polls what it shows (issue 40): every answer it polls is under 8 KiB with 64
DUTs, late in a long batch and at its end, and the compact view it polls holds no list that grows
with the batch (no transitions, no step list) and no result, program-and-verify record or verdict
text: those the page fetches once, when they change.

The 64-DUT batch is built from a real one (tests/test_web_compact_world.py: a small simulated
station runs fast-thermal-verified to its end; its DUT runs, with their results, are copied into 64
slots of a sfem-24 batch at step 61 of 72 with thousands of transitions) and served by the real
daemon and routes over HTTP. Which requests the page polls is read from its own JavaScript
(tests/test_web_compact_js.py): every request path it may ask for under a `setInterval`, but those
named below with why they are asked for only on a change. So a request the page starts polling is
measured here (one that names more than the batch fails, to be looked at).
"""

from __future__ import annotations

import re

import httpx
import pytest

from test_web_compact_js import reachable_from_timers
from test_web_compact_world import N_SLOTS, STEP_NOW, big_batch, finished_batch
from web.views import LIVE_SLOT_FIELDS
from web_support import LiveStation, auth

LIMIT = 8192
# Asked for under a timer, but not on every tick (web/static/status.js, cards.js, app.js): whatever
# else a timer may ask for is polled, and measured.
ON_CHANGE = {
    "/api/batches/${id}/slots?${only}result=false": "a slot's serial, label, fault, program and verify, verdict: "
                                                    "once per change of its rev in the compact view",
    "/api/batches/${id}/steps": "the step list: when the running step or the batch's state changes",
    "/api/runs/${s.runId}": "a finished run's result, once it is stored to its end (cards.js loadPlot keeps it)",
    "/api/runs/${s.runId}/plot.png": "that run's plot, once, with it",
    "/api/events?token=": "the live event stream: one connection, opened again only when it drops",
}
NOT_IN_COMPACT = {"transitions", "steps", "sorting", "result", "program", "verification", "program_verify",
                  "link_stats", "labels", "serial", "step_windows", "grade", "tray"}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("web_compact"), n_serial=2, n_can=1, speed=600.0, fixture=True) as live:
        src = finished_batch(live)
        running = big_batch(live, src, src + 1000, ended=False)
        ended = big_batch(live, src, src + 1001, ended=True)
        with httpx.Client(base_url=live.url, timeout=60, headers=auth("operator")) as client:
            yield {"live": live, "client": client, "running": running, "ended": ended, "small": src}


def url_of(template: str, batch_id: int) -> str:
    """A polled path with its placeholders filled: the batch's id is the one thing it may name."""
    return re.sub(r"\$\{[^}]*\}", str(batch_id), template)


def keys_in(value: object) -> set[str]:
    if isinstance(value, dict):
        return set(value) | {k for v in value.values() for k in keys_in(v)}
    if isinstance(value, list):
        return {k for v in value for k in keys_in(v)}
    return set()


def polled() -> set[str]:
    """What the page asks for on its timers' ticks: every request path under a timer but those
    asked for only on a change."""
    return {p for p in reachable_from_timers() if p not in ON_CHANGE}


def test_the_page_polls_the_compact_status_and_asks_for_the_rest_only_on_a_change():
    reachable = reachable_from_timers()
    gone = set(ON_CHANGE) - set(reachable) - {"/api/events?token="}
    assert not gone, f"named as asked for on a change, but no timer asks for it any more: {gone}"
    assert "/api/batches/${id}?view=compact" in polled() and "/api/health" in polled(), reachable
    assert not any(re.fullmatch(r"/api/batches/\$\{[^}]+\}", p) for p in reachable), \
        "the page asks for the full status under a timer: it polls ?view=compact"


@pytest.mark.parametrize("which", ["running", "ended"])
def test_every_answer_the_page_polls_is_under_8_kib(world, which):
    client, bid = world["client"], world[which]
    sizes = {}
    for template in sorted(polled()):
        r = client.get(url_of(template, bid))
        assert r.status_code == 200, (template, r.status_code, r.text[:300])
        sizes[template] = len(r.content)
        if "etag" in r.headers:  # the browser revalidates: an unchanged answer costs no body
            again = client.get(url_of(template, bid), headers={"If-None-Match": r.headers["etag"]})
            assert again.status_code in (200, 304) and (again.status_code == 200 or again.content == b"")
    print(f"\n{which}: polled answers with {N_SLOTS} DUTs: {sizes}")
    assert all(n < LIMIT for n in sizes.values()), sizes
    full = client.get(f"/api/batches/{bid}")
    assert len(full.content) > 40 * LIMIT  # what the page polled before: transitions, results, records


@pytest.mark.parametrize("which", ["running", "ended"])
def test_the_compact_view_holds_no_transitions_results_or_records(world, which):
    client, bid = world["client"], world[which]
    full = client.get(f"/api/batches/{bid}").json()
    c = client.get(f"/api/batches/{bid}", params={"view": "compact"}).json()
    assert len(full["transitions"]) > 2000 and len(full["steps"]) == 73  # the big batch is big ...
    assert any(s["result"] for s in full["slots"]) and any(s["verification"] for s in full["slots"])
    assert not keys_in(c) & NOT_IN_COMPACT, keys_in(c) & NOT_IN_COMPACT  # ... its compact view is not
    assert c["slots"] == [{"slot": s["slot"]} for s in full["slots"]]
    live = c["slot_live"]
    assert set(live) == set(LIVE_SLOT_FIELDS) | {"rev"}
    for i, s in enumerate(full["slots"]):
        assert {k: live[k][i] for k in LIVE_SLOT_FIELDS} == {k: s[k] for k in LIVE_SLOT_FIELDS}, s["slot"]
    assert len(set(live["rev"])) == N_SLOTS and all(re.fullmatch(r"[0-9a-f]{8}", r) for r in live["rev"])
    assert c["current_step"] == full["current_step"]
    assert c["decision"] == full["decision"] and c["counts"] == full["counts"] and c["overload"] == full["overload"]


def test_the_compact_view_does_not_grow_with_the_batch(world):
    """Ten thousand more transitions (a batch hours longer, prompts asked again and again) and the
    sample counts a day later: the compact view keeps its size, the full one does not."""
    live, client, bid = world["live"], world["client"], world["running"]
    seq = live.station.batches[bid]
    before_c = len(client.get(f"/api/batches/{bid}", params={"view": "compact"}).content)
    before_f = len(client.get(f"/api/batches/{bid}").content)
    history = list(seq.history)

    def grow() -> None:
        t = seq.history[-1][0]
        seq.history += [(t + k, "logging", "waiting_operator") if k % 2 else (t + k, "waiting_operator", "logging")
                        for k in range(10_000)]
        for d in seq.duts:
            d.n_samples += 86_400 * 4  # a day at 3.125 Hz, rounded up

    live.call(grow)
    try:
        after_c = len(client.get(f"/api/batches/{bid}", params={"view": "compact"}).content)
        after_f = len(client.get(f"/api/batches/{bid}").content)
    finally:
        live.call(lambda: setattr(seq, "history", history))
    assert after_f > before_f + 400_000
    assert abs(after_c - before_c) <= N_SLOTS + 64, (before_c, after_c)  # a digit more per sample count at most
    assert after_c < LIMIT


def test_a_slot_s_fields_are_fetched_by_name_and_its_rev_moves_when_they_change(world):
    live, client, bid = world["live"], world["client"], world["running"]
    seq = live.station.batches[bid]
    c0 = client.get(f"/api/batches/{bid}", params={"view": "compact"}).json()
    names = [s["slot"] for s in c0["slots"]]
    got = client.get(f"/api/batches/{bid}/slots",
                     params=[("slot", "c16"), ("slot", "s01"), ("slot", "nope"), ("result", "false")])
    assert got.status_code == 200
    slots = got.json()
    assert [s["slot"] for s in slots] == ["s01", "c16"]  # the batch's order; an unknown name left out
    assert all("result" not in s for s in slots) and slots[0]["serial"] and slots[0]["label_serial"]
    everything = client.get(f"/api/batches/{bid}/slots").json()
    assert [s["slot"] for s in everything] == names
    done = [s for s in everything if s["state"] == "done"]
    assert done and all(s["result"] and s["program"] and s["verification"] and s["verdict"] for s in done)
    faulted = [s for s in everything if s["state"] == "faulted"]
    assert faulted and all(s["error"] and s["verdict"] == "error" for s in faulted)

    i = names.index("s05")  # a running slot: its verdict comes, its rev moves, no other's
    d = seq.duts[i]
    verdict = {"verdict": "fail", "grade": None, "tray": "reject", "reason": "z TDSF -612 ppm/C, limit -500",
               "attempt": 1, "limits_name": "LIS3DSH-default", "limits_version": "2", "run_id": d.run_id}
    live.call(lambda: setattr(d, "verdict", verdict))
    try:
        live.call(lambda: live.app.state.batch_status_cache.pop(bid, None))  # the kept render is 0.5 s old
        c1 = client.get(f"/api/batches/{bid}", params={"view": "compact"}).json()
    finally:
        live.call(lambda: setattr(d, "verdict", None))
    moved = [n for n, a, b in zip(names, c0["slot_live"]["rev"], c1["slot_live"]["rev"]) if a != b]
    assert moved == ["s05"]


def test_the_step_list_is_fetched_apart_and_the_running_row_polled(world):
    client = world["client"]
    running = client.get(f"/api/batches/{world['running']}/steps").json()
    assert len(running) == 73 and [r["index"] for r in running] == list(range(73))
    assert [r["state"] for r in running[:STEP_NOW + 2]] == ["done"] * STEP_NOW + ["running", "pending"]
    c = client.get(f"/api/batches/{world['running']}", params={"view": "compact"}).json()
    assert c["current_step"]["index"] == STEP_NOW and c["current_step"]["name"] == running[STEP_NOW]["name"]
    ended = client.get(f"/api/batches/{world['ended']}/steps").json()
    newest = client.get("/api/batches", params={"limit": 1, "view": "compact"})  # how the page finds its batch
    assert newest.json() == [client.get(f"/api/batches/{world['ended']}", params={"view": "compact"}).json()]
    assert len(newest.content) < LIMIT
    assert [r["state"] for r in ended] == ["done"] * 73
    assert client.get(f"/api/batches/{world['ended']}", params={"view": "compact"}).json()["current_step"] is None
    small = client.get(f"/api/batches/{world['small']}/steps").json()
    assert [r["name"] for r in small] == ["P ambient", "P hot", "N hot", "N ambient", "program", "verify hot", "analysis"]
    assert client.get("/api/batches/999999/steps").status_code == 404
    assert client.get("/api/batches/999999/slots").status_code == 404
