"""GET /metrics (web/metrics.py, docs/metrics.md) against a real station: simulated boards on ptys
and slcan, the lamp relay on Modbus TCP on 127.0.0.1, SQLite on disk, the web app served by uvicorn
on 127.0.0.1 and scraped over real HTTP while a fast-thermal batch runs.

Every scrape is read with prometheus_client's own text parser (text_string_to_metric_families), not
with the code that wrote it; the figures are held against the database and the API.

Access: the peer address decides, never a header. A second app on the same station is served with
`[metrics] allow = ["127.0.0.1/32"]`, and a client whose socket is bound to 127.0.0.2 (Linux routes
all of 127/8 to lo) is a genuinely different source address: refused without a token, served with
an admin or mes token, refused with an operator's, and X-Forwarded-For: 127.0.0.1 changes nothing.
"""

from __future__ import annotations

import asyncio
import socket
from collections import Counter

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.web_support import LiveStation, auth, bound_socket, wait_for

pytestmark = pytest.mark.timeout(300)


def scrape(client: httpx.Client, headers: dict[str, str] | None = None) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """One scrape, parsed: (sample name, sorted labels) -> value."""
    r = client.get("/metrics", headers=headers or {})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain")
    out = {}
    for family in text_string_to_metric_families(r.text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def total(samples, name: str, **labels: str) -> float:
    """Sum of a sample name's values whose labels include `labels`."""
    return sum(v for (n, ls), v in samples.items() if n == name and all((k, w) in ls for k, w in labels.items()))


def types_of(text: str) -> dict[str, str]:
    return {f.name: f.type for f in text_string_to_metric_families(text)}


async def serve_with_allow(station, allow: list[str], sock):
    """A second web app on the same (real) station, built while its config says `[metrics] allow =
    allow` (create_app reads the list when it builds the app); the config is restored at once."""
    from station.config import Metrics
    from web.app import create_app
    from web.server import serve_web

    saved = station.config.metrics
    station.config.metrics = Metrics(allow=allow)
    try:
        app = create_app(station, outbox=False)
    finally:
        station.config.metrics = saved
    server, task = await serve_web(station, "127.0.0.1", sock.getsockname()[1], app=app, sock=sock)
    for _ in range(200):
        if server.started:
            break
        await asyncio.sleep(0.05)
    return server, task


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("metrics"), n_serial=2, n_can=1, speed=400.0, fixture=True) as ls:
        yield ls


@pytest.fixture(scope="module")
def client(live):
    with httpx.Client(base_url=live.url, timeout=30) as c:
        yield c


def test_batch_scraped_while_it_runs(live, client):
    """Scraped before, during and after a fast-thermal batch of 3 DUTs: the sample counters rise
    between scrapes while it runs, and at its end the verdict figures are the database's."""
    before = scrape(client)
    assert before[("station_info", (("name", "test-station"), ("version", _version())))] == 1.0
    slots = [s["slot"] for s in client.get("/api/slots", headers=auth("operator")).json()]
    assert sorted(slots) == ["c1", "s1", "s2"]
    r = client.post("/api/batches", json={"profile": "fast-thermal", "slots": None, "operator": "Ana"},
                    headers=auth("operator"))
    assert r.status_code in (200, 201), r.text
    bid = r.json()["id"]

    # several scrapes while it runs: each slot's samples rise, the batch is in a running state
    seen: list[dict] = []

    def running_scrape():
        s = scrape(client)
        if s[("station_batch_running", ())] == 1.0 and total(s, "station_samples_received_total") > 0:
            seen.append(s)
        return len(seen) >= 3 or s[("station_batch_running", ())] == 0.0 and seen

    wait_for(running_scrape, 120, interval_s=0.3, what="three scrapes during the batch")
    assert len(seen) >= 2, "the batch ended before it could be scraped twice"
    first, last = seen[0], seen[-1]
    totals = [total(s, "station_samples_received_total") for s in seen]
    assert totals == sorted(totals) and totals[-1] > totals[0], totals  # a counter: never down, and up
    assert first[("station_batch_id", ())] == bid
    for slot, kind in (("s1", "serial"), ("s2", "serial"), ("c1", "can")):
        a = total(first, "station_samples_received_total", slot=slot, link=kind)
        b = total(last, "station_samples_received_total", slot=slot, link=kind)
        assert b > a >= 0, (slot, a, b)
    assert total(last, "station_batch_duts", state="running") + total(last, "station_batch_duts", state="done") == 3
    assert total(first, "station_batch_state") == 1.0  # exactly one state is 1
    assert first[("station_batches_started_total", ())] == before[("station_batches_started_total", ())] + 1
    assert total(last, "station_intake_samples_per_second") >= 0
    assert ("station_writer_queue_depth", ()) in last

    def ended():
        st = client.get(f"/api/batches/{bid}", headers=auth("operator")).json()
        return st if st["state"] in ("finished", "failed", "aborted", "interrupted") else None

    status = wait_for(ended, 180, interval_s=0.3, what="batch end")
    assert status["state"] == "finished", status.get("error")
    live.flush_db()

    # the verdicts as the database holds them (read straight from its tables), and as the API's
    # batch status gives them
    from tests.exports_support import db_truth

    _, runs = db_truth(live.station.db, bid)
    db_verdicts = Counter(r["verdict"] for r in runs.values())
    assert sum(db_verdicts.values()) == 3, runs
    api_verdicts = Counter((s.get("verdict") or {}).get("verdict") if isinstance(s.get("verdict"), dict) else s.get("verdict")
                           for s in client.get(f"/api/batches/{bid}", headers=auth("operator")).json()["slots"])
    assert api_verdicts == db_verdicts, (api_verdicts, db_verdicts)
    end = wait_for(lambda: (lambda s: s if total(s, "station_batch_duts_verdict", verdict="pending") == 0 else None)(
        scrape(client)), 30, what="every DUT judged in /metrics")
    for v in ("pass", "marginal", "fail", "error"):
        assert total(end, "station_batch_duts_verdict", verdict=v) == db_verdicts.get(v, 0), (v, db_verdicts)
        assert (total(end, "station_duts_judged_total", verdict=v) - total(before, "station_duts_judged_total", verdict=v)
                == db_verdicts.get(v, 0)), v
    assert total(end, "station_batch_state", state="finished") == 1.0
    assert end[("station_batch_running", ())] == 0.0
    assert total(end, "station_batches_ended_total", state="finished") == total(before, "station_batches_ended_total",
                                                                               state="finished") + 1
    # every sample the station took in went to the database (the writer counts what it committed)
    taken = total(end, "station_samples_received_total") - total(before, "station_samples_received_total")
    assert taken > 0
    assert end[("station_writer_samples_committed_total", ())] >= taken
    assert end[("station_writer_queue_depth", ())] >= 0
    # the lamp: off now, and it was on for a while in this batch (wall seconds, a few at x400)
    assert end[("station_lamp_on", ())] == 0.0
    assert end[("station_lamp_on_seconds_total", ())] > before[("station_lamp_on_seconds_total", ())]
    assert end[("station_lamp_switched_on_total", ())] >= before[("station_lamp_switched_on_total", ())] + 1
    assert total(end, "station_alarms_active", kind="storage") == 0


def _version() -> str:
    from web import __version__

    return __version__


def test_types_and_help_are_declared(client):
    """Every family has its TYPE and HELP (a scraper that reads types sees counters as counters)."""
    r = client.get("/metrics")
    types = types_of(r.text)
    assert types["station_samples_received"] == "counter"
    assert types["station_lamp_on_seconds"] == "counter"
    assert types["station_writer_queue_depth"] == "gauge"
    assert types["station_batch_state"] == "gauge"
    assert types["station_info"] == "gauge"  # an info metric: the text format 0.0.4 has no info type
    assert r.text.count("# HELP ") == r.text.count("# TYPE ")
    assert "/metrics" not in client.get("/openapi.json").json()["paths"]


def test_loopback_allowed_without_token(client):
    assert client.get("/metrics").status_code == 200  # the default allow list: loopback
    # through a proxy on the PC every client is a loopback peer: the forwarding header asks for a token
    r = client.get("/metrics", headers={"X-Forwarded-For": "192.0.2.7"})
    assert r.status_code == 403 and "\n" not in r.json()["detail"], r.text
    assert client.get("/metrics", headers={"X-Forwarded-For": "192.0.2.7", **auth("admin")}).status_code == 200


@pytest.fixture(scope="module")
def strict_server(live):
    """The same station served by a second app whose [metrics] allow is 127.0.0.1/32 only."""
    from web.server import stop_web

    sock = bound_socket()
    server, task = live.call(serve_with_allow, live.station, ["127.0.0.1/32"], sock)
    yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    live.call(stop_web, server, task, timeout_s=10)


def test_peer_outside_allow_list_refused(strict_server):
    """A client on 127.0.0.2 (a genuinely different source address) against allow=127.0.0.1/32."""
    probe = socket.socket()
    try:
        probe.bind(("127.0.0.2", 0))
    except OSError:
        pytest.skip("127.0.0.2 cannot be bound here")
    finally:
        probe.close()
    transport = httpx.HTTPTransport(local_address="127.0.0.2")
    with httpx.Client(base_url=strict_server, transport=transport, timeout=30) as other, \
            httpx.Client(base_url=strict_server, timeout=30) as loop:
        r = other.get("/metrics")
        assert r.status_code == 403, r.text
        assert "127.0.0.2" in r.json()["detail"] and "\n" not in r.json()["detail"]
        # a header is what a client says: it changes nothing
        spoofed = other.get("/metrics", headers={"X-Forwarded-For": "127.0.0.1", "X-Real-IP": "127.0.0.1",
                                                 "Forwarded": "for=127.0.0.1"})
        assert spoofed.status_code == 403
        assert other.get("/metrics", headers=auth("admin")).status_code == 200
        assert other.get("/metrics", headers=auth("mes")).status_code == 200
        op = other.get("/metrics", headers=auth("operator"))
        assert op.status_code == 403 and "operator" in op.json()["detail"]
        bad = other.get("/metrics", headers={"Authorization": "Bearer not-a-token-at-all"})
        assert bad.status_code == 401
        # 127.0.0.1 itself is still in the list: no token needed
        assert loop.get("/metrics").status_code == 200
        parsed = scrape(other, auth("admin"))
        assert ("station_batch_running", ()) in parsed


def test_allow_list_without_loopback(live):
    """allow = ["10.0.0.0/8"]: 127.0.0.1 needs a token too (another app on the station, real HTTP)."""
    from web.server import stop_web

    sock = bound_socket()
    server, task = live.call(serve_with_allow, live.station, ["10.0.0.0/8"], sock)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{sock.getsockname()[1]}", timeout=30) as c:
            r = c.get("/metrics")
            assert r.status_code == 403 and "127.0.0.1" in r.json()["detail"], r.text
            assert c.get("/metrics", headers=auth("admin")).status_code == 200
            assert c.get("/metrics", headers=auth("operator")).status_code == 403
            # a client on the station PC (a loopback peer) that says it is on the allowed network:
            # uvicorn rewrites request.client from X-Forwarded-For for a 127.0.0.1 peer, so a
            # request with any forwarding header is let in by a token only
            for header in ({"X-Forwarded-For": "10.1.2.3"}, {"X-Forwarded-For": "10.1.2.3, 10.1.2.4"},
                           {"Forwarded": "for=10.1.2.3"}, {"X-Real-IP": "10.1.2.3"}):
                r = c.get("/metrics", headers=header)
                assert r.status_code == 403 and "proxy" in r.json()["detail"], (header, r.text)
                assert c.get("/metrics", headers={**header, **auth("mes")}).status_code == 200
    finally:
        live.call(stop_web, server, task, timeout_s=10)


def test_allow_list_validated():
    from station.config import Metrics

    assert Metrics().allow == ["127.0.0.1/32", "::1/128"]
    assert Metrics(allow=[]).allow == []
    for bad in (["127.0.0.1/33"], ["10.0.0.1/8"], ["localhost"]):
        with pytest.raises(ValueError):
            Metrics(allow=bad)


def test_tally_counts_each_lamp_period_and_batch_once():
    """The event tally alone: a second ON while on is the same period; an OFF closes it; a batch
    is started at its first event whatever its coarse state, ended once."""
    from contracts.events import BatchStateChanged, DutVerdict, LampChanged
    from web.metrics import EventTally

    t = EventTally()
    t.note(LampChanged(1, on=True, reason="heat", wall_time=100.0))
    t.note(LampChanged(1, on=True, reason="heat again", wall_time=130.0))
    assert t.lamp_on_s(now_s=150.0) == 50.0 and t.lamp_switched_on == 1
    t.note(LampChanged(1, on=False, reason="done", wall_time=160.0))
    t.note(LampChanged(1, on=False, reason="batch end", wall_time=170.0))
    assert t.lamp_on_s(now_s=500.0) == 60.0
    for state in ("running", "paused", "running", "finished"):
        t.note(BatchStateChanged(1, state=state))
    t.note(BatchStateChanged(2, state="aborted"))
    assert t.batches_started == 2 and t.batches_ended == {"finished": 1, "aborted": 1}
    t.note(DutVerdict(1, slot="s1", serial="A", verdict={"verdict": "marginal"}))
    assert t.verdicts == {"marginal": 1}
