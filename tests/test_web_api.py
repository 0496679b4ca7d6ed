"""REST API (design 5.3) over real HTTP on loopback, against a whole simulated station.

One LiveStation per module (2 serial boards on ptys, 1 CAN board behind slcan, Modbus TCP lamp
relay and fixture on 127.0.0.1, the real daemon, SQLite on disk). One fast-thermal batch runs to the
end through the API while an SSE client listens; every other test reads what it left behind (rows
in the database, the CSV log, the plot), or checks auth and input validation on every route.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import httpx
import numpy as np
import pytest

from contracts.logfile import parse_log
from web_support import TOKENS, LiveStation, auth, seed_results, wait_for

TERMINAL = {"finished", "aborted", "failed", "interrupted"}
TDB_TOL_MG_PER_C = 0.05
TDSF_TOL_PPM_PER_C = 60.0


# --- fixtures -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("web_api"), n_serial=2, n_can=1, speed=400.0, fixture=True,
                     access_log=True) as ls:
        yield ls


@pytest.fixture(scope="module")
def client(live):
    with httpx.Client(base_url=live.url, timeout=30) as c:
        yield c


class SseCollector(threading.Thread):
    """Reads GET /api/events over a real socket; stops by itself when the batch ends."""

    def __init__(self, url: str, token: str, stop_on_batch_end: bool = True) -> None:
        super().__init__(daemon=True)
        self.url, self.token, self.stop_on_batch_end = url, token, stop_on_batch_end
        self.events: list[dict] = []
        self.ids: list[int] = []
        self.status: int | None = None
        self.content_type = ""
        self.opened = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with httpx.Client(timeout=httpx.Timeout(10, read=60)) as c:
                with c.stream("GET", self.url + "/api/events", params={"token": self.token}) as r:
                    self.status = r.status_code
                    self.content_type = r.headers.get("content-type", "")
                    self.opened.set()
                    for line in r.iter_lines():
                        if line.startswith("id: "):
                            self.ids.append(int(line[4:]))
                        elif line.startswith("data: "):
                            ev = json.loads(line[6:])
                            self.events.append(ev)
                            if (self.stop_on_batch_end and ev.get("kind") == "BatchStateChanged"
                                    and ev.get("state") in TERMINAL):
                                return
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc
        finally:
            self.opened.set()

    def kinds(self, kind: str) -> list[dict]:
        return [e for e in self.events if e.get("kind") == kind]


@pytest.fixture(scope="module")
def batch(live, client):
    """Start a fast-thermal batch over HTTP with an SSE client listening; run it to the end."""
    sse = SseCollector(live.url, TOKENS["operator"])
    sse.start()
    assert sse.opened.wait(15)
    wait_for(lambda: sse.kinds("Snapshot"), 10, what="SSE snapshot")
    r = client.post("/api/batches", json={"profile": "fast-thermal", "slots": None, "operator": "Ana"},
                    headers=auth("operator"))
    assert r.status_code == 201, r.text
    batch_id = r.json()["id"]
    assert r.headers["location"] == f"/api/batches/{batch_id}"
    seen_states = set()
    running_snapshots = []

    def ended():
        st = client.get(f"/api/batches/{batch_id}", headers=auth("mes")).json()
        seen_states.add(st["state"])
        if st["state"] == "running":
            running_snapshots.append(st)
        # the batch reports its end a moment before its DUTs do (station/daemon/sequencer.py: "finished"
        # is set before release_duts marks them done): wait for both
        return st if st["state"] in TERMINAL and all(s["state"] in ("done", "faulted") for s in st["slots"]) else None

    status = wait_for(ended, 120, interval_s=0.2, what="batch end")
    sse.join(20)
    live.flush_db()
    return {"id": batch_id, "status": status, "sse": sse, "seen": seen_states, "running": running_snapshots}


@pytest.fixture(scope="module")
def seeded(live, batch):
    """Five more stored results written through the real DbWriter (for paging)."""
    return seed_results(live.station.db, 5, serial_prefix="PAGE", seed=3)


def get(client, path, role="admin", **kw):
    return client.get(path, headers=auth(role), **kw)


# --- the batch flow -------------------------------------------------------------------------------

def test_batch_runs_to_the_end_with_results_for_every_dut(live, client, batch):
    st = batch["status"]
    assert st["state"] == "finished", st.get("error")
    assert st["id"] == batch["id"] and st["profile"] == "fast-thermal" and st["operator"] == "Ana"
    assert st["step"]["count"] == 4 and st["step"]["name"] == "N ambient"
    assert "running" in batch["seen"]
    # live status showed slots moving while it ran
    assert any(s["segments"] > 0 for snap in batch["running"] for s in snap["slots"])
    slots = get(client, "/api/slots", "operator").json()
    serials = {s["slot"]: s["serial"] for s in slots}
    assert [s["slot"] for s in st["slots"]] == ["s1", "s2", "c1"]
    for s in st["slots"]:
        assert s["state"] == "done" and s["segments"] == 4 and s["error"] is None
        assert s["serial"] == serials[s["slot"]]


def test_dut_results_match_the_simulated_truth(live, client, batch):
    truths = live.sim.truths
    for i, s in enumerate(batch["status"]["slots"]):
        dut = get(client, f"/api/duts/{s['serial']}", "mes").json()
        assert dut["serial"] == s["serial"] and dut["batch_id"] == batch["id"]
        assert dut["finished_at"]
        assert dut["run_id"] == s["run_id"]
        tdb = np.array([dut["thermal"][a]["tdb_mg_per_c"] for a in "xyz"])
        tdsf = np.array([dut["thermal"][a]["tdsf_ppm_per_c"] for a in "xyz"])
        assert np.all(np.abs(tdb - np.asarray(truths[i].tdb_mg_per_c)) < TDB_TOL_MG_PER_C), (tdb, truths[i])
        assert np.all(np.abs(tdsf - np.asarray(truths[i].tdsf_ppm_per_c)) < TDSF_TOL_PPM_PER_C), (tdsf, truths[i])
        # both methods are stored; the chosen one is what `thermal` shows
        assert dut["streaming"]["method"] == "streaming" and dut["offline"]["method"] == "offline"
        chosen = dut[dut["thermal_method"]]
        assert [chosen[a]["tdb_mg_per_c"] for a in "xyz"] == list(tdb)


def test_runs_segments_log_and_plot_of_every_dut(client, batch):
    for s in batch["status"]["slots"]:
        runs = get(client, f"/api/duts/{s['serial']}/runs", "operator").json()
        assert len(runs) >= 1
        run = next(r for r in runs if r["batch_id"] == batch["id"])
        assert run["id"] == s["run_id"] and run["slot"] == s["slot"] and run["state"] == "done"
        assert run["profile"] == "fast-thermal" and run["thermal"]

        one = get(client, f"/api/runs/{run['id']}", "operator").json()
        assert one["serial"] == s["serial"]

        segs = get(client, f"/api/runs/{run['id']}/segments", "operator").json()
        assert [g["index"] for g in segs] == [0, 1, 2, 3]
        for g in segs:
            assert g["t_end_s"] > g["t_start_s"] and g["n_samples"] > 0 and len(g["acc_mean_g"]) == 3
        # P ambient, P hot, N hot, N ambient: sign of gravity flips, the hot ones are >= 15 C warmer
        assert segs[0]["acc_mean_g"][0] * segs[2]["acc_mean_g"][0] < 0
        assert segs[1]["temp_mean_c"] - segs[0]["temp_mean_c"] > 15
        assert segs[2]["temp_mean_c"] - segs[3]["temp_mean_c"] > 15

        r = get(client, f"/api/runs/{run['id']}/log.csv", "operator")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
        assert f'{s["serial"]}-run{run["id"]}.csv' in r.headers["content-disposition"]
        log = parse_log(r.text)
        assert log.serial == s["serial"]
        assert len(log) > 1000 and log.acc_g.shape == (len(log), 3)
        assert np.all(np.diff(log.time_s) > 0)
        assert abs(len(log) - s["samples"]) <= 0.02 * s["samples"], (len(log), s["samples"])
        # the segments' mean temperature is what the log shows over the segment's time span
        g = segs[1]
        span = (log.time_s >= g["t_start_s"]) & (log.time_s <= g["t_end_s"])
        assert abs(float(log.temp_c[span].mean()) - g["temp_mean_c"]) < 1.0

        png = get(client, f"/api/runs/{run['id']}/plot.png", "operator")
        assert png.status_code == 200 and png.headers["content-type"] == "image/png"
        assert png.content[:8] == b"\x89PNG\r\n\x1a\n" and len(png.content) > 20_000


def test_sse_delivered_the_batch_live(batch):
    sse = batch["sse"]
    assert sse.error is None, sse.error
    assert sse.status == 200 and sse.content_type.startswith("text/event-stream")
    assert sse.events[0]["kind"] == "Snapshot" and len(sse.events[0]["slots"]) == 3
    assert sse.ids == sorted(sse.ids) and len(set(sse.ids)) == len(sse.ids)
    kinds = {e["kind"] for e in sse.events}
    assert "SamplesReceived" not in kinds  # too heavy: summarised
    steps = [e["step_name"] for e in sse.kinds("StepStarted") if e["batch_id"] == batch["id"]]
    assert steps == ["P ambient", "P hot", "N hot", "N ambient"]
    segs = sse.kinds("SegmentLogged")
    assert sorted(e["slot"] for e in segs) == sorted(["s1", "s2", "c1"] * 4)
    results = {e["serial"]: e for e in sse.kinds("DutResult")}
    assert set(results) == {s["serial"] for s in batch["status"]["slots"]}
    for e in results.values():
        assert set(e["thermal"]["axes"]) == {"x", "y", "z"}
    summaries = sse.kinds("LiveSummary")
    assert len(summaries) >= 5
    temps = [v["temp_c"] for e in summaries for v in e["slots"].values() if "temp_c" in v]
    assert max(temps) - min(temps) > 15  # the lamp heated the plate, and the page saw it
    assert sse.events[-1]["kind"] == "BatchStateChanged" and sse.events[-1]["state"] == "finished"


def test_results_feed_pages_with_a_cursor(client, batch, seeded):
    r = get(client, "/api/results", "mes", params={"limit": 3})
    assert r.status_code == 200
    pages, items = 0, []
    page = r.json()
    while True:
        pages += 1
        items += page["results"]
        assert page["next"] == str(items[-1]["id"])  # never null: the last page's cursor is where to poll from
        if len(page["results"]) < 3:  # not full: the last page for now
            break
        page = get(client, "/api/results", "mes", params={"limit": 3, "since": page["next"]}).json()
    assert pages == 3 and len(items) == 8
    again = get(client, "/api/results", "mes", params={"limit": 3, "since": page["next"]}).json()
    assert again == {"results": [], "next": page["next"]}  # polling from there reads nothing twice
    ids = [it["id"] for it in items]
    assert ids == sorted(ids) and len(set(ids)) == 8
    keys = [it["idempotency_key"] for it in items]
    assert len(set(keys)) == 8
    by_serial = {it["serial"]: it for it in items}
    for s in batch["status"]["slots"]:
        it = by_serial[s["serial"]]
        assert it["run_id"] == s["run_id"] and it["batch_id"] == batch["id"] and it["slot"] == s["slot"]
        assert set(it["thermal"]) == {"x", "y", "z"}
    for serial, truth in seeded.items():
        got = [by_serial[serial]["thermal"][a]["tdb_mg_per_c"] for a in "xyz"]
        assert np.allclose(got, truth["tdb"])
    # an ISO time: results created at/after it
    future = (datetime.now(timezone.utc) + timedelta(hours=1)).isoformat()
    assert get(client, "/api/results", "mes", params={"since": future}).json() == {"results": [], "next": future}
    past = (datetime.now(timezone.utc) - timedelta(hours=1)).isoformat().replace("+00:00", "Z")
    assert len(get(client, "/api/results", "admin", params={"since": past, "limit": 100}).json()["results"]) == 8
    # the last id as cursor: nothing newer
    assert get(client, "/api/results", "mes", params={"since": str(ids[-1])}).json()["results"] == []


def test_dut_search_finds_partial_serials(client, batch, seeded):
    found = get(client, "/api/duts", "operator", params={"serial_like": "page0"}).json()
    assert sorted(d["serial"] for d in found) == sorted(seeded)
    assert all(d["runs"] == 1 for d in found)
    serial = batch["status"]["slots"][0]["serial"]
    one = get(client, "/api/duts", "operator", params={"serial_like": serial}).json()
    assert [d["serial"] for d in one] == [serial] and one[0]["last_state"] == "done"
    assert get(client, "/api/duts", "operator", params={"serial_like": "no-such"}).json() == []


def test_second_batch_prompt_abort_and_conflicts(live, client, batch):
    r = client.post("/api/batches", json={"profile": "hold", "slots": ["s1", "c1"], "operator": "Bo"},
                    headers=auth("operator"))
    assert r.status_code == 201, r.text
    bid = r.json()["id"]
    assert bid > batch["id"]
    try:
        # one plate, one lamp: a second batch while this one runs is refused with a reason
        r2 = client.post("/api/batches", json={"profile": "fast-thermal", "operator": "Bo"}, headers=auth("admin"))
        assert r2.status_code == 409 and "already running" in r2.json()["detail"]
        st = get(client, f"/api/batches/{bid}", "operator").json()
        assert [s["slot"] for s in st["slots"]] == ["s1", "c1"]
        listed = get(client, "/api/batches", "operator").json()
        assert [b["id"] for b in listed][:2] == [bid, batch["id"]]
        assert st["state"] == "running" and st["profile"] == "hold"
        # the motorized fixture turns the plate: no operator prompt is open
        assert get(client, f"/api/batches/{bid}/prompt", "operator").json() is None
        r3 = client.post(f"/api/batches/{bid}/prompt", json={"prompt_id": 1}, headers=auth("operator"))
        assert r3.status_code == 409 and "no prompt" in r3.json()["detail"]
    finally:
        ra = client.post(f"/api/batches/{bid}/abort", headers=auth("operator"))
    assert ra.status_code == 200 and ra.json()["ok"] is True
    def ended():  # the batch, then (a moment later, see the batch fixture) its DUTs
        s = get(client, f"/api/batches/{bid}", "operator").json()
        return s if s["state"] in TERMINAL and all(x["state"] not in ("connecting", "identified", "running")
                                                   for x in s["slots"]) else None

    st = wait_for(ended, 30, what="abort")
    assert st["state"] == "aborted" and st["error"]
    assert {s["state"] for s in st["slots"]} == {"interrupted"}
    again = client.post(f"/api/batches/{bid}/abort", headers=auth("operator"))
    assert again.status_code == 409 and "already ended" in again.json()["detail"]
    # the aborted runs are stored as such
    live.flush_db()
    serial = st["slots"][0]["serial"]
    runs = get(client, f"/api/duts/{serial}/runs", "operator").json()
    assert next(r for r in runs if r["batch_id"] == bid)["state"] in ("aborted", "interrupted", "faulted")


# --- health, page, OpenAPI ------------------------------------------------------------------------

def test_health_is_open(client):
    r = client.get("/api/health")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ok" and body["db"] == "ok" and body["version"]


def test_page_and_assets_are_served_by_the_station_with_no_cdn(client):
    r = client.get("/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert "default-src 'self'" in r.headers["content-security-policy"]
    for asset in ("/static/app.js", "/static/app.css"):
        a = client.get(asset)
        assert a.status_code == 200 and len(a.content) > 1000
        assert a.headers["cache-control"] == "no-cache" and a.headers["x-content-type-options"] == "nosniff"
    static = Path(__file__).resolve().parents[1] / "web" / "static"
    for f in (p for p in static.rglob("*") if p.is_file()):  # the message catalogs in i18n/ too
        text = f.read_text()
        assert "http://" not in text and "https://" not in text and "//cdn" not in text, f


def test_api_reference_is_served_by_the_station(client):
    r = client.get("/docs")
    assert r.status_code == 200 and '<script src="/static/api.js"' in r.text
    assert client.get("/redoc").status_code == 404


def test_openapi_documents_every_contract_path(client):
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/api/batches", "/api/batches/{batch_id}", "/api/batches/{batch_id}/abort",
              "/api/batches/{batch_id}/prompt", "/api/duts/{serial}", "/api/duts/{serial}/runs",
              "/api/runs/{run_id}/segments", "/api/runs/{run_id}/log.csv", "/api/results", "/api/events",
              "/api/health"):
        assert p in paths, p
    assert set(paths["/api/batches/{batch_id}/prompt"]) == {"get", "post"}


# --- auth -----------------------------------------------------------------------------------------

PROTECTED = [
    ("GET", "/api/me", None), ("GET", "/api/slots", None), ("GET", "/api/profiles", None), ("GET", "/api/batches", None),
    ("POST", "/api/batches", {"profile": "fast-thermal", "operator": "x"}),
    ("GET", "/api/batches/1", None), ("POST", "/api/batches/1/abort", None), ("POST", "/api/batches/1/resume", None),
    ("GET", "/api/batches/1/prompt", None), ("POST", "/api/batches/1/prompt", {"prompt_id": 1}),
    ("GET", "/api/duts", None), ("GET", "/api/duts/SIM0001", None), ("GET", "/api/duts/SIM0001/runs", None),
    ("GET", "/api/runs/1", None), ("GET", "/api/runs/1/segments", None), ("GET", "/api/runs/1/log.csv", None),
    ("GET", "/api/runs/1/plot.png", None), ("GET", "/api/results", None), ("GET", "/api/outbox", None),
    ("GET", "/api/events", None),
]


@pytest.mark.parametrize("method,path,body", PROTECTED, ids=[f"{m} {p}" for m, p, _ in PROTECTED])
def test_missing_or_invalid_token_is_401(client, method, path, body):
    r = client.request(method, path, json=body)
    assert r.status_code == 401
    assert "missing token" in r.json()["detail"] and r.headers["www-authenticate"] == "Bearer"
    bad = "not-a-valid-token-xyz"
    r = client.request(method, path, json=body, headers={"Authorization": f"Bearer {bad}"})
    assert r.status_code == 401 and r.json()["detail"] == "invalid token" and bad not in r.text
    r = client.request(method, path, json=body, headers={"Authorization": TOKENS["admin"]})  # no "Bearer"
    assert r.status_code == 401 and "malformed" in r.json()["detail"] and TOKENS["admin"] not in r.text


FORBIDDEN = [
    ("mes", "POST", "/api/batches", {"profile": "fast-thermal", "operator": "x"}),
    ("mes", "POST", "/api/batches/1/abort", None),
    ("mes", "POST", "/api/batches/1/resume", None),
    ("mes", "POST", "/api/batches/1/prompt", {"prompt_id": 1}),
    ("operator", "GET", "/api/results", None),
    ("operator", "GET", "/api/outbox", None),
    ("mes", "GET", "/api/outbox", None),
]


@pytest.mark.parametrize("role,method,path,body", FORBIDDEN, ids=[f"{r} {m} {p}" for r, m, p, _ in FORBIDDEN])
def test_wrong_role_is_403(client, role, method, path, body):
    r = client.request(method, path, json=body, headers=auth(role))
    assert r.status_code == 403
    assert f"role '{role}' may not do this" in r.json()["detail"]


@pytest.mark.parametrize("role", ["operator", "mes", "admin"])
def test_me_names_the_token_owner_and_role_never_the_token(client, role):
    r = get(client, "/api/me", role)
    assert r.status_code == 200 and r.json() == {"name": f"test-{role}", "role": role}
    assert TOKENS[role] not in r.text


def test_profiles_and_slots_describe_the_station(client):
    profiles = {p["name"] for p in get(client, "/api/profiles", "mes").json()}
    assert {"fast-thermal", "hold"} <= profiles
    slots = get(client, "/api/slots", "mes").json()
    assert [s["slot"] for s in slots] == ["s1", "s2", "c1"]
    assert all(s["serial"] and s["serial"].startswith("SIM") for s in slots)


def test_admin_may_read_the_outbox(client):
    r = get(client, "/api/outbox", "admin")
    assert r.status_code == 200 and isinstance(r.json(), list)


def test_event_stream_accepts_the_token_in_the_query_only_for_sse(client):
    assert client.get("/api/slots", params={"token": TOKENS["admin"]}).status_code == 401
    with client.stream("GET", "/api/events", params={"token": TOKENS["mes"]}) as r:
        assert r.status_code == 200
        line = next(ln for ln in r.iter_lines() if ln.startswith("data: "))
        assert json.loads(line[6:])["kind"] == "Snapshot"


class _Capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_tokens_never_appear_in_logs(live, client):
    cap = _Capture()
    names = ("", "uvicorn", "uvicorn.access", "uvicorn.error", "station", "station.web", "httpx")
    loggers = [logging.getLogger(n) for n in names]
    for lg in loggers:
        lg.addHandler(cap)
    try:
        with client.stream("GET", "/api/events", params={"token": TOKENS["operator"]}) as r:
            next(ln for ln in r.iter_lines() if ln.startswith("data: "))
        client.get("/api/events", params={"token": "wrong-token-in-query"})
        client.get("/api/slots", headers=auth("admin"))
        client.get("/api/results", headers=auth("operator"))  # 403
        client.get("/api/slots", headers={"Authorization": "Bearer some-wrong-token"})
        wait_for(lambda: any("/api/events" in m for m in cap.messages), 5, what="access log of /api/events")
        time.sleep(0.3)
    finally:
        for lg in loggers:
            lg.removeHandler(cap)
    text = "\n".join(cap.messages)
    assert "/api/events?token=***" in text and "/api/slots" in text  # the access log did log the requests
    for secret in (*TOKENS.values(), "wrong-token-in-query", "some-wrong-token"):
        assert secret not in text


# --- bad input: 422 with a message; unknown ids: 404 ------------------------------------------------

BAD_INPUT = [
    ("POST", "/api/batches", {}, "profile"),
    ("POST", "/api/batches", {"profile": "fast-thermal"}, "operator"),
    ("POST", "/api/batches", {"profile": "no-such-profile", "operator": "x"}, "unknown profile"),
    ("POST", "/api/batches", {"profile": "fast-thermal", "operator": "x", "slots": []}, "non-empty"),
    ("POST", "/api/batches", {"profile": "fast-thermal", "operator": "x", "slots": ["s1", "s1"]}, "repeat"),
    ("POST", "/api/batches", {"profile": "fast-thermal", "operator": "x", "slots": ["zz9"]}, "unknown slot"),
    ("POST", "/api/batches", {"profile": "fast-thermal", "operator": "   "}, "blank"),
    ("POST", "/api/batches", {"profile": "fast-thermal", "operator": "x", "colour": "red"}, "colour"),
    ("POST", "/api/batches", "not json", "body"),
    ("GET", "/api/batches/abc", None, "batch_id"),
    ("GET", "/api/batches/0", None, "batch_id"),
    ("POST", "/api/batches/1/prompt", {"answer": "done"}, "prompt_id"),
    ("POST", "/api/batches/1/prompt", {"prompt_id": -4}, "prompt_id"),
    ("GET", "/api/duts/bad%20serial", None, "serial"),
    ("GET", "/api/duts", {"limit": 0}, "limit"),
    ("GET", "/api/runs/x/segments", None, "run_id"),
    ("GET", "/api/results", {"since": "yesterday"}, "ISO 8601"),
    ("GET", "/api/results", {"limit": 5000}, "limit"),
]


@pytest.mark.parametrize("method,path,body,needle", BAD_INPUT, ids=[f"{m} {p} {n}" for m, p, _, n in BAD_INPUT])
def test_bad_input_is_422_with_a_message(client, method, path, body, needle):
    kw = {}
    if method == "GET":
        kw["params"] = body
    elif isinstance(body, str):
        kw["content"] = body
        kw["headers"] = {**auth("admin"), "Content-Type": "application/json"}
    else:
        kw["json"] = body
    kw.setdefault("headers", auth("admin"))
    r = client.request(method, path, **kw)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert isinstance(detail, str) and needle.lower() in detail.lower(), detail


NOT_FOUND = [
    ("GET", "/api/batches/987654", None), ("POST", "/api/batches/987654/abort", None),
    ("POST", "/api/batches/987654/resume", None),
    ("GET", "/api/batches/987654/prompt", None), ("POST", "/api/batches/987654/prompt", {"prompt_id": 1}),
    ("GET", "/api/duts/NO-SUCH-DUT", None), ("GET", "/api/duts/NO-SUCH-DUT/runs", None),
    ("GET", "/api/runs/987654", None), ("GET", "/api/runs/987654/segments", None),
    ("GET", "/api/runs/987654/log.csv", None), ("GET", "/api/runs/987654/plot.png", None),
]


@pytest.mark.parametrize("method,path,body", NOT_FOUND, ids=[f"{m} {p}" for m, p, _ in NOT_FOUND])
def test_unknown_ids_are_404(client, method, path, body):
    r = client.request(method, path, json=body, headers=auth("admin"))
    assert r.status_code == 404
    assert "987654" in r.json()["detail"] or "NO-SUCH-DUT" in r.json()["detail"]


def test_resume_of_a_batch_that_was_not_interrupted_is_409(client, batch):
    """The success path (SIGKILL mid-batch, restart, resume) is tests/test_resume_after_sigkill.py."""
    r = client.post(f"/api/batches/{batch['id']}/resume", headers=auth("operator"))
    assert r.status_code == 409
    assert "only an interrupted batch can be resumed" in r.json()["detail"]
