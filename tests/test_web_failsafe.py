"""Fail-safe web API (issue 10): what a hostile or careless client can no longer do.

The app runs under real uvicorn on a free 127.0.0.1 port (bodies, sockets and disconnects are the
server's, not a test client's); the station behind it is a stand-in with a real EventBus, because
these cases are about the HTTP layer (the whole simulated station is in test_web_api.py and
test_web_schemathesis.py).
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from contextlib import contextmanager
from types import SimpleNamespace

import httpx
import pytest

from contracts.events import EventBus
from web.app import create_app
from web.auth import TokenStore
from web.diag_plots import BoundedCache, Busy
from web.guard import DEFAULT_MAX_BODY_BYTES
from web.repo import NoRepository
from web.schemas import ValidationErrorOut
from web_support import bound_socket, wait_for

TOKENS = {"operator": "op-token-0123456789", "mes": "mes-token-0123456789", "admin": "admin-token-0123456789"}
BIG = 50 * 1024 * 1024  # the 50 MB POSTs


def auth(role: str) -> dict:
    return {"Authorization": f"Bearer {TOKENS[role]}"}


class BodyCounter:
    """Outermost ASGI wrapper: how many request-body bytes the app ever took from the server."""

    def __init__(self, app) -> None:
        self.app = app
        self.bytes = 0

    async def __call__(self, scope, receive, send) -> None:
        async def counted():
            msg = await receive()
            self.bytes += len(msg.get("body", b""))
            return msg

        await self.app(scope, counted if scope["type"] == "http" else receive, send)


class SlowLogRepo(NoRepository):
    """Runs 1..9 exist; their logs load only when `release` is set (a long diagnosis), then are
    missing (404). Counts the loads: the independent truth of how much work was done."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.loading = threading.Event()
        self.log_reads = 0

    def run(self, run_id):
        return {"id": run_id} if 1 <= run_id <= 9 else None

    def run_log(self, run_id):
        self.log_reads += 1
        self.loading.set()
        assert self.release.wait(30)
        return None

    def results_since(self, after_id=0, since_time=None, limit=100):
        return []


@contextmanager
def serve(app):
    """uvicorn on a free loopback port in a thread with its own loop (as the daemon runs it)."""
    import uvicorn

    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           timeout_graceful_shutdown=1, lifespan="on"))
    thread = threading.Thread(target=lambda: server.run(sockets=[sock]), daemon=True)
    thread.start()
    wait_for(lambda: server.started, 20, 0.02, "uvicorn started")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


@pytest.fixture(scope="module")
def live():
    station = SimpleNamespace(config=None, bus=EventBus(), db=None, slots_status=lambda: [])
    repo = SlowLogRepo()
    app = create_app(station, repo=repo, outbox=False, max_event_streams=2, sse_interval_s=0.1,
                     tokens=TokenStore([(t, r, f"test-{r}") for r, t in TOKENS.items()]))
    counter = BodyCounter(app)
    with serve(counter) as url:
        yield SimpleNamespace(url=url, app=app, repo=repo, counter=counter, port=int(url.rsplit(":", 1)[1]))


@pytest.fixture()
def client(live):
    with httpx.Client(base_url=live.url, timeout=30) as c:
        yield c


def raw_post(port: int, headers: dict[str, str], body_prefix: bytes, path: str = "/api/batches") -> tuple[int, bytes, int]:
    """Declare a body of Content-Length, send only `body_prefix`, read the answer.

    Returns (status, raw answer, bytes of body sent): an answer here proves the server decided
    without the rest of the body."""
    head = f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in headers.items())
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(head.encode() + b"\r\n")
        sent = 0
        try:
            s.sendall(body_prefix)
            sent = len(body_prefix)
        except OSError:  # the server may close as soon as it has answered
            pass
        data = b""
        while b"\r\n\r\n" not in data or len(data) < data.index(b"\r\n\r\n") + 4 + _length(data):
            chunk = s.recv(65536)
            if not chunk:
                break
            data += chunk
    return int(data.split(b" ", 2)[1]), data, sent


def _length(data: bytes) -> int:
    for line in data.split(b"\r\n\r\n", 1)[0].split(b"\r\n")[1:]:
        k, _, v = line.partition(b":")
        if k.strip().lower() == b"content-length":
            return int(v)
    return 0


# --- 1. bodies: the token before the body, and a size cap -----------------------------------------

@pytest.mark.parametrize("authorization,needle", [(None, b"missing token"), ("Bearer not-a-valid-token", b"invalid token")])
def test_a_big_post_without_a_valid_token_is_401_before_its_body_is_read(live, authorization, needle):
    """Four 50 MB POSTs without a token once took the daemon from 459 to 902 MB: now each is
    answered 401 after 64 KiB of the declared 50 MB were sent, and the app read none of it."""
    before = live.counter.bytes
    for _ in range(4):
        headers = {"Content-Type": "application/json", "Content-Length": str(BIG)}
        if authorization:
            headers["Authorization"] = authorization
        status, answer, sent = raw_post(live.port, headers, b"x" * 65536)
        assert status == 401, answer[:300]
        assert needle in answer and b"www-authenticate: Bearer" in answer.lower().replace(b"bearer", b"Bearer")
        assert sent <= 65536
    assert live.counter.bytes == before  # not one body byte reached the app


def test_a_big_post_with_a_token_is_413_before_its_body_is_read(live):
    before = live.counter.bytes
    status, answer, _ = raw_post(live.port, {**auth("operator"), "Content-Type": "application/json",
                                             "Content-Length": str(BIG)}, b"{" * 65536)
    assert status == 413, answer[:300]
    assert b"larger than 1048576 bytes" in answer and b"max_body_bytes" in answer
    assert live.counter.bytes == before


def test_a_chunked_body_is_cut_off_at_the_limit(live):
    """No Content-Length to judge by: the guard counts what arrives and stops at the limit."""
    chunk = b"x" * 65536
    n_chunks = 64  # 4 MiB offered
    head = ("POST /api/batches HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            f"Authorization: Bearer {TOKENS['operator']}\r\nTransfer-Encoding: chunked\r\n\r\n").encode()
    sent = 0
    before = live.counter.bytes
    with socket.create_connection(("127.0.0.1", live.port), timeout=10) as s:
        s.sendall(head)
        try:
            for _ in range(n_chunks):
                s.sendall(b"%x\r\n%s\r\n" % (len(chunk), chunk))
                sent += len(chunk)
        except OSError:
            pass
        answer = s.recv(65536)
    assert answer.startswith(b"HTTP/1.1 413"), answer[:300]
    # read up to the limit plus the server's last piece (uvicorn hands over up to ~256 KiB at a time)
    assert live.counter.bytes - before <= DEFAULT_MAX_BODY_BYTES + 512 * 1024


def test_a_body_under_the_limit_reaches_the_route(client):
    """The guard is not a blanket refusal: 900 kB of valid JSON with a token gets to validation."""
    pad = "p" * 900_000
    r = client.post("/api/batches", json={"profile": pad, "operator": "x"}, headers=auth("operator"))
    assert r.status_code == 422 and "profile" in r.json()["detail"]
    assert DEFAULT_MAX_BODY_BYTES == 1 << 20


def test_a_json_body_that_is_not_utf8_is_422_like_other_bad_json(client):
    bad_json = client.post("/api/batches", content=b'{"profile": ', headers={**auth("operator"), "Content-Type": "application/json"})
    not_utf8 = client.post("/api/batches", content=b'{"profile": "\xff\xfe", "operator": "x"}',
                           headers={**auth("operator"), "Content-Type": "application/json"})
    for r in (bad_json, not_utf8):
        assert r.status_code == 422, r.text
        assert r.json()["detail"].startswith("body: not valid JSON")
        ValidationErrorOut.model_validate(r.json())  # what the document says a 422 is
    assert "not UTF-8 at byte 13" in not_utf8.json()["detail"]


# --- 2. results?since= ----------------------------------------------------------------------------

@pytest.mark.parametrize("since,needle", [
    ("9223372036854775808", "out of range"),  # one past int64
    ("\u00b2", "expected a cursor"),  # '²': str.isdigit() is True, int() fails
    ("0001-01-01", "out of range"),  # local midnight of year 1 is before the epoch's range
    ("2026-02-30", "not a valid date"),
    ("2026-01-31T08:00:00", "expected a cursor"),  # no offset: ambiguous, refused
])
def test_results_since_out_of_range_or_malformed_is_422_with_a_message(client, since, needle):
    r = client.get("/api/results", params={"since": since}, headers=auth("mes"))
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith("since: ") and needle in r.json()["detail"]


@pytest.mark.parametrize("since", ["", "0", "9223372036854775807", "2026-01-31", "2026-01-31T08:00:00Z",
                                   "2026-01-31t08:00:60.5+01:00"])
def test_results_since_accepts_the_documented_forms(client, since):
    r = client.get("/api/results", params={"since": since}, headers=auth("mes"))
    assert r.status_code == 200 and r.json() == {"results": [], "next": since or "0"}  # never null: poll from there


# --- 3. the OpenAPI document says what is sent ----------------------------------------------------

def test_openapi_has_bearer_security_and_the_error_answers_of_every_route(client):
    doc = client.get("/openapi.json").json()
    schemes = doc["components"]["securitySchemes"]
    assert schemes["bearer"] == {**schemes["bearer"], "type": "http", "scheme": "bearer"}
    assert "HTTPValidationError" not in doc["components"]["schemas"]
    for path, item in doc["paths"].items():
        for method, op in item.items():
            codes = set(op["responses"])
            if path == "/api/health":
                assert "security" not in op
                continue
            assert {"bearer": []} in op["security"], (method, path)
            assert {"401", "403"} <= codes, (method, path, codes)
            if "422" in codes:
                assert op["responses"]["422"]["content"]["application/json"]["schema"] == {
                    "$ref": "#/components/schemas/ValidationErrorOut"}
            if "requestBody" in op:
                assert {"401", "413", "422"} <= codes
            if "/diagnosis" in path:
                assert {"401", "403", "404", "409", "422", "429"} <= codes
                assert "Retry-After" in op["responses"]["429"]["headers"]
    assert {"query_token": []} in doc["paths"]["/api/events"]["get"]["security"]


def test_a_405_names_every_method_of_the_path(client):
    r = client.request("PUT", "/api/batches", headers=auth("admin"))
    assert r.status_code == 405 and r.headers["allow"] == "GET, POST"


# --- 4. bounded work: diagnoses, plots, event streams ---------------------------------------------

def test_one_diagnosis_at_a_time_others_429_with_retry_after_and_repeats_share_it(live):
    """Run 1's diagnosis is loading (its log is slow): a second request for run 1 waits for that
    same computation, a request for run 2 is refused at once with 429 and Retry-After."""
    repo = live.repo
    repo.release.clear()
    repo.loading.clear()
    reads0 = repo.log_reads
    results: dict[str, httpx.Response] = {}

    def get(name, path):
        with httpx.Client(base_url=live.url, timeout=30) as c:
            results[name] = c.get(path, headers=auth("mes"))

    first = threading.Thread(target=get, args=("first", "/api/runs/1/diagnosis"))
    first.start()
    assert repo.loading.wait(10)
    same = threading.Thread(target=get, args=("same", "/api/runs/1/diagnosis"))
    same.start()
    wait_for(lambda: live.app.state.diagnosis_cache.reports._waiting == 1, 10, 0.02, "the repeat waits")
    with httpx.Client(base_url=live.url, timeout=30) as c:
        t0 = time.monotonic()
        other = c.get("/api/runs/2/diagnosis", headers=auth("mes"))
        refused_in_s = time.monotonic() - t0
    assert other.status_code == 429, other.text
    assert int(other.headers["retry-after"]) >= 1 and "busy" in other.json()["detail"]
    assert refused_in_s < 2.0  # refused, not queued
    repo.release.set()
    first.join(30)
    same.join(30)
    assert results["first"].status_code == 404 and results["same"].status_code == 404
    assert repo.log_reads - reads0 == 1  # one computation for both


def test_bounded_cache_is_an_lru_that_refuses_beyond_its_limits():
    cache: BoundedCache[int] = BoundedCache("work", size=2, max_running=1, max_waiting=1)
    calls = []
    for k in (1, 2, 1, 3):  # 3 evicts 2 (1 was used more recently)
        assert cache.get(k, lambda k=k: calls.append(k) or k * 10) == k * 10
    assert calls == [1, 2, 3] and len(cache) == 2
    assert cache.get(2, lambda: calls.append(2) or 20) == 20 and calls[-1] == 2
    assert cache.get(9, lambda: 90, store=False) == 90 and 9 not in cache._values

    gate, started = threading.Event(), threading.Event()

    def slow():
        started.set()
        gate.wait(10)
        return 5

    t = threading.Thread(target=cache.get, args=(5, slow))
    t.start()
    assert started.wait(5)
    with pytest.raises(Busy) as busy:
        cache.get(6, lambda: 60)  # another key while one runs: refused
    assert busy.value.retry_after_s >= 1
    waiter = threading.Thread(target=cache.get, args=(5, slow))
    waiter.start()
    wait_for(lambda: cache._waiting == 1, 5, 0.01, "one waiter")
    with pytest.raises(Busy):
        cache.get(5, slow)  # the waiting room is full too
    gate.set()
    t.join(5)
    waiter.join(5)
    assert cache.get(5, lambda: 55) == 5 and cache.refused == 2


def test_event_streams_are_capped_per_station_and_a_closed_one_frees_its_place(live):
    """max_event_streams=2 here (default 32): a third stream is 503 with Retry-After."""
    url = f"{live.url}/api/events"

    def open_stream(c: httpx.Client):
        cm = c.stream("GET", url, params={"token": TOKENS["mes"]})
        r = cm.__enter__()
        return cm, r

    with httpx.Client(timeout=httpx.Timeout(10, read=30)) as c1, httpx.Client(timeout=httpx.Timeout(10, read=30)) as c2:
        a_cm, a = open_stream(c1)
        b_cm, b = open_stream(c2)
        assert a.status_code == 200 and b.status_code == 200
        lines_a = a.iter_lines()  # kept: dropping the iterator would close the stream
        assert next(lines_a).startswith("id: ")
        third = httpx.get(url, params={"token": TOKENS["mes"]}, timeout=10)
        assert third.status_code == 503, third.text
        assert third.headers["retry-after"] == "5" and "2 event streams are already open" in third.json()["detail"]
        a_cm.__exit__(None, None, None)
        wait_for(lambda: live.app.state.event_streams.open == 1, 10, 0.05, "the closed stream released")
        with httpx.stream("GET", url, params={"token": TOKENS["mes"]}, timeout=10) as again:
            assert again.status_code == 200
        b_cm.__exit__(None, None, None)
    wait_for(lambda: live.app.state.event_streams.open == 0, 10, 0.05, "all streams released")


def test_a_stream_refused_by_auth_takes_no_place(live):
    for _ in range(5):
        assert httpx.get(f"{live.url}/api/events", params={"token": "nope-nope-nope"}, timeout=10).status_code == 401
    assert live.app.state.event_streams.open == 0
