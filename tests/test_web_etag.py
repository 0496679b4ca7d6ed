"""GET /api/batches/{id} revalidates (web/routes/batches.py get_batch, web/status_etag.py): a strong
ETag of the answer's bytes, `Cache-Control: no-cache`, 304 with no body when If-None-Match holds the
current tag, a new tag whenever the answer changes (samples, a prompt, an abort, the batch's end),
never a 304 that hides a change, and a compact view with only what the operator page shows.

A real station (LiveStation: simulated boards on a pty and CAN, the Modbus relay, the daemon,
SQLite) over real HTTP. Changes that must invalidate the kept render are made on the daemon itself
(not through the REST routes, which also drop the kept render), and the render TTL is stretched to
a minute where a test checks that only the batch's change marker decides: a stale 304 would then
show, instead of hiding behind the 0.5 s TTL.
"""

from __future__ import annotations

import hashlib
import json
import threading
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

import web.routes.batches as batches_route
from web.schemas import BatchStatus, SlotStatus, StepInfo, TimeLeft
from web.status_etag import (COMPACT_BATCH_FIELDS, COMPACT_SLOT_FIELDS, COMPACT_STEP_FIELDS,
                             COMPACT_TIME_LEFT_FIELDS, etag_of, none_match)
from web_support import LiveStation, auth, wait_for

TERMINAL = {"finished", "aborted", "failed", "interrupted"}
# two steps at two plate positions: the operator is asked to turn the plate before each
PROFILES = {"two-holds": {"description": "test: P for a moment, then N until aborted", "analysis": "none",
                          "steps": [{"name": "a", "position": "P", "lamp": False, "require": "none",
                                     "dwell_s": 5, "timeout_s": 1e6},
                                    {"name": "b", "position": "N", "lamp": False, "require": "none",
                                     "dwell_s": 1e6, "timeout_s": 2e6}]}}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("web_etag"), n_serial=1, n_can=1, speed=400.0, fixture=False,
                     operator_hands=True, profiles=PROFILES) as ls:
        yield ls


@pytest.fixture(scope="module")
def client(live):
    with httpx.Client(base_url=live.url, timeout=30, headers=auth("operator")) as c:
        yield c


@pytest.fixture
def long_ttl(monkeypatch):
    """Only the change marker may end the kept render (the TTL would otherwise hide a stale one)."""
    monkeypatch.setattr(batches_route, "STATUS_TTL_S", 60.0)


def seq_of(live, bid):
    return live.station.batches[bid]


def daemon_state(live, bid) -> str:
    """The truth: the daemon's own state of the batch (read in its loop)."""
    return live.call(lambda: live.station.batch_status(bid)["state"])


def start(client, profile: str = "two-holds") -> int:
    r = client.post("/api/batches", json={"profile": profile, "operator": "etag-test"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def end(live, bid) -> None:
    """Abort on the daemon (not through REST, which would also drop the kept render)."""
    if daemon_state(live, bid) not in TERMINAL:
        live.call(live.station.abort, bid, "test over", by="test")
    wait_for(lambda: daemon_state(live, bid) in TERMINAL, 30, what=f"batch {bid} ended")


def get(client, bid, etag: str | None = None, view: str | None = None) -> httpx.Response:
    headers = {"If-None-Match": etag} if etag else {}
    r = client.get(f"/api/batches/{bid}", headers=headers, params={"view": view} if view else None)
    assert r.status_code in (200, 304), r.text
    return r


def test_match_is_304_with_no_body_and_the_same_tag(live, client, long_ttl):
    bid = start(client)
    try:
        # waiting for the operator: nothing changes the batch's marker until the prompt is answered
        wait_for(lambda: live.call(lambda: seq_of(live, bid).prompt) is not None, 30, what="the first prompt")
        r = get(client, bid)
        tag = r.headers["etag"]
        assert tag.startswith('"') and tag.endswith('"') and not tag.startswith("W/"), tag  # strong
        assert r.headers["cache-control"] == "no-cache"
        assert tag == etag_of(bid, "full", r.content)  # a digest of exactly the bytes sent
        again = get(client, bid)  # the kept render: the same bytes, the same tag
        assert again.content == r.content and again.headers["etag"] == tag
        hit = get(client, bid, tag)
        assert hit.status_code == 304 and hit.content == b""
        assert hit.headers["etag"] == tag and hit.headers["cache-control"] == "no-cache"
        assert int(hit.headers.get("content-length", "0")) == 0
        # a list of tags, weak comparison, and '*' match too (RFC 9110 13.1.2)
        assert get(client, bid, f'"other", W/{tag}').status_code == 304
        assert get(client, bid, "*").status_code == 304
        assert get(client, bid, '"b1-full-000000000000000000000000"').status_code == 200
    finally:
        end(live, bid)


def test_new_sample_count_is_a_new_tag(live, client):
    bid = start(client)
    try:
        wait_for(lambda: sum(s["samples"] or 0 for s in get(client, bid).json()["slots"]) > 0, 30, what="samples")
        first = get(client, bid)
        n0 = sum(s["samples"] for s in first.json()["slots"])
        # past the render's TTL (0.5 s) the boards have sent more: the answer and its tag change
        later = wait_for(lambda: (r := get(client, bid, first.headers["etag"])).status_code == 200
                         and sum(s["samples"] for s in r.json()["slots"]) > n0 and r, 10, what="more samples")
        assert later.headers["etag"] != first.headers["etag"]
        assert later.headers["etag"] == etag_of(bid, "full", later.content)
    finally:
        end(live, bid)


def test_a_prompt_raised_or_answered_is_a_new_tag(live, client, long_ttl):
    bid = start(client)
    try:
        wait_for(lambda: live.call(lambda: seq_of(live, bid).prompt) is not None, 30, what="the first prompt")
        asked = get(client, bid)
        assert asked.json()["prompt"] is not None and asked.json()["state"] == "paused"
        assert get(client, bid, asked.headers["etag"]).status_code == 304
        prompt_id = live.call(lambda: seq_of(live, bid).prompt["id"])
        live.call(live.station.answer_prompt, bid, prompt_id, "done", by="test")  # on the daemon, not REST
        wait_for(lambda: live.call(lambda: seq_of(live, bid).prompt) is None, 30, what="the prompt answered")
        answered = get(client, bid, asked.headers["etag"])
        assert answered.status_code == 200 and answered.json()["prompt"] is None
        assert answered.headers["etag"] != asked.headers["etag"]
        # step a's dwell passes, then the plate must be turned to N: a new prompt, a new tag
        wait_for(lambda: (p := live.call(lambda: seq_of(live, bid).prompt)) is not None and p["id"] != prompt_id,
                 30, what="the second prompt")
        raised = get(client, bid, answered.headers["etag"])
        assert raised.status_code == 200 and raised.json()["prompt"]["prompt_id"] != prompt_id
    finally:
        end(live, bid)


def test_an_ended_batch_is_never_a_304_for_its_running_tag(live, client, long_ttl):
    bid = start(client)
    wait_for(lambda: live.call(lambda: seq_of(live, bid).prompt) is not None, 30, what="the first prompt")
    running = get(client, bid)
    assert running.json()["state"] not in TERMINAL
    tag = running.headers["etag"]
    assert get(client, bid, tag).status_code == 304  # the kept render, while nothing changed
    live.call(live.station.abort, bid, "test", by="test")  # the daemon's own end: no REST route drops the cache
    # every answer from now on, with the running tag, shows the truth of that moment; once the
    # daemon says ended, the answer must say so (a stale 304 would keep 'running' on the page)
    wait_for(lambda: daemon_state(live, bid) in TERMINAL, 30, what="the batch ended")
    ended = get(client, bid, tag)
    assert ended.status_code == 200, "a client holding the running batch's tag must see it ended"
    assert ended.json()["state"] == "aborted" and ended.headers["etag"] != tag
    assert get(client, bid, ended.headers["etag"]).status_code == 304


def test_an_abort_through_rest_is_a_new_tag(live, client):
    bid = start(client)
    tag = get(client, bid).headers["etag"]
    assert client.post(f"/api/batches/{bid}/abort").status_code == 200
    wait_for(lambda: get(client, bid, tag).status_code == 200 and get(client, bid).json()["state"] in TERMINAL,
             30, what="the aborted batch")
    assert get(client, bid, tag).status_code == 200


def test_two_batches_never_share_a_tag(live, client, long_ttl):
    a = start(client)
    end(live, a)
    b = start(client)
    try:
        ra, rb = get(client, a), get(client, b)
        assert ra.headers["etag"] != rb.headers["etag"]
        assert get(client, b, ra.headers["etag"]).status_code == 200
        assert get(client, a, rb.headers["etag"]).status_code == 200
        assert get(client, a, ra.headers["etag"]).status_code == 304
        # even the same bytes under two batch ids get two tags
        assert etag_of(a, "full", b"{}") != etag_of(b, "full", b"{}")
    finally:
        end(live, b)


def test_compact_view_carries_what_the_page_shows(live, client, long_ttl):
    bid = start(client)
    try:
        wait_for(lambda: live.call(lambda: seq_of(live, bid).prompt) is not None, 30, what="the first prompt")
        full, compact = get(client, bid), get(client, bid, view="compact")
        f, c = full.json(), compact.json()
        assert len(compact.content) < len(full.content) / 2
        assert set(c) <= set(COMPACT_BATCH_FIELDS) and {"id", "state", "slots", "prompt", "step"} <= set(c)
        for k in c:
            if k not in ("slots", "step", "time_left"):
                assert c[k] == f[k], k
        assert c["step"] == {k: f["step"][k] for k in COMPACT_STEP_FIELDS}
        assert c["time_left"] == {k: f["time_left"].get(k) for k in COMPACT_TIME_LEFT_FIELDS}
        assert [s["slot"] for s in c["slots"]] == [s["slot"] for s in f["slots"]]
        for cs, fs in zip(c["slots"], f["slots"]):
            assert cs == {k: fs[k] for k in COMPACT_SLOT_FIELDS if fs.get(k) is not None}
        assert compact.headers["etag"] == etag_of(bid, "compact", compact.content) != full.headers["etag"]
        assert get(client, bid, compact.headers["etag"], view="compact").status_code == 304
        assert get(client, bid, full.headers["etag"], view="compact").status_code == 200
        bad = client.get(f"/api/batches/{bid}", params={"view": "tiny"})
        assert bad.status_code == 422 and "view" in bad.json()["detail"]
    finally:
        end(live, bid)


def test_pollers_at_once_share_one_render(live, client, long_ttl):
    """Requests that come while the status is rendered wait for that render: one daemon status per
    TTL whatever the number of pollers (the render yields to the loop between its parts)."""
    bid = start(client)
    try:
        wait_for(lambda: live.call(lambda: seq_of(live, bid).prompt) is not None, 30, what="the first prompt")
        station = live.station
        calls = []
        real = station.batch_status

        def counted(batch_id):
            calls.append(batch_id)
            return real(batch_id)

        live.call(lambda: setattr(station, "batch_status", counted))
        try:
            assert get(client, bid).status_code == 200  # the render kept for the TTL ...
            live.call(lambda: live.app.state.batch_status_cache.pop(bid))  # ... dropped, as an abort does
            calls.clear()
            n = 12
            gate = threading.Barrier(n)

            def one(_):
                with httpx.Client(base_url=live.url, timeout=30, headers=auth("mes")) as c:
                    gate.wait()
                    return c.get(f"/api/batches/{bid}")

            with ThreadPoolExecutor(n) as pool:
                answers = list(pool.map(one, range(n)))
        finally:
            live.call(lambda: delattr(station, "batch_status"))
        assert all(r.status_code == 200 for r in answers)
        assert len({r.content for r in answers}) == 1 and len({r.headers["etag"] for r in answers}) == 1
        assert calls == [bid], f"{len(calls)} renders for {n} requests"
    finally:
        end(live, bid)


def test_compact_fields_are_declared_in_the_document():
    """The compact view stays a subset of the documented answer (tests/test_openapi_truth.py)."""
    assert set(COMPACT_BATCH_FIELDS) <= set(BatchStatus.model_fields)
    assert set(COMPACT_SLOT_FIELDS) <= set(SlotStatus.model_fields)
    assert set(COMPACT_STEP_FIELDS) <= set(StepInfo.model_fields)
    assert set(COMPACT_TIME_LEFT_FIELDS) <= set(TimeLeft.model_fields)


@pytest.mark.parametrize("header, match", [
    (None, False), ("", False), ('"abc"', True), ('W/"abc"', True), ('"x", "abc"', True), ("*", True),
    ('"abcd"', False), ("abc", False), ('"ab"', False),
])
def test_if_none_match_parsing(header, match):
    assert none_match(header, '"abc"') is match


def test_etag_is_a_digest_of_the_bytes():
    body = json.dumps({"id": 3, "state": "running"}).encode()
    assert etag_of(3, "full", body) == f'"b3-full-{hashlib.blake2b(body, digest_size=12).hexdigest()}"'
    assert etag_of(3, "full", body + b" ") != etag_of(3, "full", body)
