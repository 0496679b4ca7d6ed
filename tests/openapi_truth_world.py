"""The live station of tests/test_openapi_truth.py, with data behind every GET route: a
program-and-verify batch run to its end over HTTP (the operator confirming each plate prompt), an
aborted batch, stored runs with results, verdict checks, program-and-verify rows, a replay, audit
rows and MES outbox rows (the webhook worker posting to a capture server on 127.0.0.1 that refuses
each record's first try). `collect` records every answer; `sweep` calls every GET route the
document lists, so a route added later is exercised without editing the test.
"""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx

from web_support import TOKENS, LiveStation, auth, free_port, seed_results, wait_for

SPEED = 600.0
TERMINAL = {"finished", "aborted", "failed", "interrupted"}
NOT_JSON = {"image/png", "text/csv", "application/pdf", "text/event-stream", "application/octet-stream",
            "application/x-ndjson"}


class MesCapture:
    """The MES on 127.0.0.1: records every webhook body; refuses each key's first try (503) so the
    outbox holds a failed attempt with its error, then accepts."""

    def __init__(self) -> None:
        self.bodies: list[dict] = []
        self.tries: dict[str, int] = {}
        cap = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server's name
                body = json.loads(self.rfile.read(int(self.headers.get("content-length") or 0)) or b"{}")
                key = self.headers.get("idempotency-key", "")
                cap.tries[key] = cap.tries.get(key, 0) + 1
                cap.bodies.append(body)
                self.send_response(503 if cap.tries[key] == 1 else 200)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", free_port()), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/mes"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


class Answers:
    """Every GET made, as (path template, url, status, content type, body or None)."""

    def __init__(self, client: httpx.Client, station_status=None) -> None:
        self.client = client
        self.rows: list[tuple[str, str, int, str, object]] = []
        self.station_status = station_status  # batch id -> the daemon's own status, before any model
        self.raw: list[dict] = []  # those statuses, shaped by web/views.py batch_view only

    def get(self, template: str, role: str = "admin", **path) -> httpx.Response:
        params = path.pop("params", None)
        url = template.format(**path)
        r = self.client.get(url, headers=auth(role), params=params)
        ctype = r.headers.get("content-type", "").split(";")[0]
        self.rows.append((template, str(r.url), r.status_code, ctype, r.json() if ctype == "application/json" else None))
        return r

    def sse(self) -> None:
        """GET /api/events: the first `data:` line (the snapshot) is JSON; the stream is closed after it."""
        with self.client.stream("GET", "/api/events", params={"token": TOKENS["mes"]}) as r:
            first = None
            for line in r.iter_lines():
                if line.startswith("data: "):
                    first = json.loads(line[6:])
                    break
        self.rows.append(("/api/events", "/api/events", r.status_code, r.headers.get("content-type", "").split(";")[0],
                          None))
        assert first is not None and first.get("kind") == "Snapshot", first


def run_batch_to_end(a: Answers, profile: str, timeout_s: float = 300.0) -> int:
    """Start a batch over HTTP and poll every live GET while it runs; the operator confirms each
    'turn the plate' prompt over HTTP (the audit trail records it)."""
    c = a.client
    r = c.post("/api/batches", headers=auth("operator"),
               json={"profile": profile, "operator": "Ana", "work_order": "WO-7", "part_number": "PN-3",
                     "part_revision": "B", "lot": "L-42"})
    assert r.status_code == 201, r.text
    bid = r.json()["id"]
    deadline = time.monotonic() + timeout_s
    while True:
        st = a.get("/api/batches/{batch_id}", batch_id=bid).json()
        a.raw.append(a.station_status(bid))
        a.get("/api/batches/{batch_id}", batch_id=bid, params={"view": "compact"})  # the operator page's view
        prompt = a.get("/api/batches/{batch_id}/prompt", batch_id=bid).json()
        a.get("/api/slots")
        a.get("/api/batches", params={"limit": 5})
        if prompt is not None:
            ans = c.post(f"/api/batches/{bid}/prompt", headers=auth("operator"), json={"prompt_id": prompt["prompt_id"]})
            assert ans.status_code in (200, 409), ans.text  # 409: the prompt closed meanwhile
        if st["state"] in TERMINAL and all(s["state"] in ("done", "faulted") for s in st["slots"]):
            return bid
        assert time.monotonic() < deadline, f"batch {bid} did not end: {st['state']}"
        time.sleep(0.1)


def abort_a_batch(a: Answers) -> int:
    """A 'hold' batch (runs until aborted): status while running, then aborted (ended_by)."""
    c = a.client
    r = c.post("/api/batches", headers=auth("operator"), json={"profile": "hold", "operator": "Bo"})
    assert r.status_code == 201, r.text
    bid = r.json()["id"]
    # The plate ends the main batch at N and "hold" holds it at P: the batch asks a person to turn
    # it (state "paused", its prompt open) after a moment in "running" too short to catch under
    # load. The status while paused is answered and checked like any other; then the person turns
    # the plate (operator_hands) and the batch logs ("running") until it is aborted.
    seen: list[str] = []

    def live() -> str | None:
        state = a.get("/api/batches/{batch_id}", batch_id=bid).json()["state"]
        if not seen or seen[-1] != state:
            seen.append(state)
        if state == "paused":
            prompt = a.get("/api/batches/{batch_id}/prompt", batch_id=bid).json()
            if prompt is not None:
                ans = c.post(f"/api/batches/{bid}/prompt", headers=auth("operator"),
                             json={"prompt_id": prompt["prompt_id"]})
                assert ans.status_code in (200, 409), ans.text
        return state if state == "running" else None

    try:
        wait_for(live, 60, what="hold batch running")
    except AssertionError as e:
        raise AssertionError(f"{e}; states seen: {' -> '.join(seen)}") from None
    assert c.post(f"/api/batches/{bid}/abort", headers=auth("operator")).status_code == 200
    wait_for(lambda: a.get("/api/batches/{batch_id}", batch_id=bid).json()["state"] in TERMINAL, 30,
             what="hold batch aborted")
    return bid


def store_records(db) -> dict:
    """Stored history beside the live batches: DUT runs with samples, segments, thermal results and
    verdicts (web_support.seed_results), program and verify of two of them (one refused), judged
    batches with verdict checks for SPC (records_support), and a replay of a stored batch with
    its comparison (station/replay/compare.py)."""
    from db.writer import DbWriter
    from contracts.events import DutProgrammed, DutVerified
    from contracts.run_records import ProgramRecord
    from records_support import write_batches

    truth = seed_results(db, 3, serial_prefix="TRU", seed=11)
    (ok, t), (refused, t2) = list(truth.items())[:2]
    w = DbWriter(db, interval_s=0.05)
    try:
        for tt in (t, t2):
            w.bind_run(tt["batch_id"], tt["slot"], tt["run_id"])
        w.submit(DutProgrammed(t["batch_id"], slot=t["slot"], serial=ok, program=ProgramRecord.from_json({
            "programmed": True, "crc": "1A2B3C4D", "readback_crc": "1A2B3C4D", "comp": True, "attempts": 2,
            "tdb_mg_per_c": [0.1, 0.2, 0.3], "tdsf_ppm_per_c": [-100.0, -110.0, -120.0],
            "retries": ["attempt 1: crc_mismatch: read back 1A2B3C4E"]})))
        w.submit(DutVerified(t["batch_id"], slot=t["slot"], serial=ok, verification={
            "passed": True, "flags": [], "e_before_mg": {"x": 40.0, "y": 12.5, "z": 70.0},
            "e_after_mg": {"x": 0.8, "y": 1.1, "z": 2.4}}))
        w.submit(DutProgrammed(t2["batch_id"], slot=t2["slot"], serial=refused, program=ProgramRecord.from_json({
            "programmed": False, "error_kind": "refused", "error": "CALW refused after 3 attempts", "comp": False})))
        assert w.flush(30)
    finally:
        w.close()
    judged = write_batches(db, n_batches=2, per_batch=4, serial_prefix="REC")
    return {"serials": [ok, refused, judged[-1]["serial"]], "stored_batch": t["batch_id"],
            "runs": [t["run_id"], t2["run_id"], judged[-1]["run"]], "replay": store_replay(db, t["batch_id"])}


def store_replay(db, source_batch: int) -> int:
    """A replay batch of `source_batch` with the comparison the replay runner stores: one DUT as
    recorded, one whose TDSF changed (and its verdict with it)."""
    from sqlalchemy import update

    from db import repository as R
    from db.models import Batch
    from station.replay.compare import ReplayDiff, compare_outcomes

    runs = [R.run_detail(db, r["id"]) for r in R.batch_detail(db, source_batch)["runs"]][:2]
    before = [{"verdict": r["verdict"], "thermal": r["thermal"]} for r in runs]
    after = json.loads(json.dumps(before))
    after[1]["thermal"]["z"]["tdsf_ppm_per_c"] -= 400.0
    after[1]["verdict"] = "fail"
    duts = [compare_outcomes(r["slot"], r["serial"], b, a) for r, b, a in zip(runs, before, after)]
    for d in duts:
        d.samples_identical, d.note = True, "sent 600 of 600 recorded samples"
    rid = db.create_batch("fast-thermal", "replayer", {}, state="finished",
                          replay_of=f"batch {source_batch} of test-station (station.db)")
    diff = ReplayDiff(f"batch {source_batch}", "recorded", 1e-6, 1e-9, duts,
                      agreement={"agrees": None, "note": "the recording has no lamp/position columns"},
                      replay_batch_id=rid, replay_state="finished", recorded_state="finished")
    with db.session() as s:
        s.execute(update(Batch).where(Batch.id == rid).values(replay_diff=diff.to_json()))
    return rid


def sweep(a: Answers, doc: dict, batches: list[int], stored: dict) -> int:
    """Every GET route of the document over the data the station now holds: each path parameter
    filled with every id of its kind (the slow diagnosis with one run), plus query variants."""
    for role in ("operator", "mes", "admin"):
        a.get("/api/me", role=role)
    live_slots = a.client.get(f"/api/batches/{batches[0]}", headers=auth("mes")).json()["slots"]
    ids = {"batch_id": [*batches, stored["stored_batch"]],
           "serial": [s["serial"] for s in live_slots if s.get("serial")] + stored["serials"],
           "run_id": [s["run_id"] for s in live_slots if s.get("run_id")] + stored["runs"]}
    diag = a.get("/api/runs/{run_id}/diagnosis", run_id=ids["run_id"][0])
    assert diag.status_code == 200, diag.text
    for template in (p for p, item in doc["paths"].items() if "get" in item):
        if template == "/api/events":
            a.sse()
        elif template.startswith("/api/replays/"):
            a.get(template, batch_id=stored["replay"])
        elif template.endswith("/prompt"):
            a.get(template, batch_id=batches[0])
        elif "/diagnosis" in template:
            a.get(template, run_id=ids["run_id"][0], plot=diag.json()["plots"][0])
        else:
            names = [n for n in ids if "{" + n + "}" in template]
            assert len(names) <= 1, template
            for value in (ids[names[0]] if names else [None]):
                a.get(template, **({names[0]: value} if names else {}))
    for bid in ids["batch_id"]:
        a.get("/api/yield", params={"batch_id": bid})
    a.get("/api/batches/{batch_id}", batch_id=stored["replay"])  # a stored replay batch: with its comparison
    # an added effect: the staircase's fitted parameters (per axis and nonlinear)
    a.get("/api/runs/{run_id}/diagnosis", run_id=ids["run_id"][0], params=[("add", "thermal_lag"), ("add", "bias_t2")])
    since = "0"
    while True:  # the MES feed page by page, to its end
        page = a.get("/api/results", role="mes", params={"since": since, "limit": 4}).json()
        if not page["results"]:
            break
        since = page["next"]
    for p in (a.client.get("/api/spc", headers=auth("mes")).json().get("parameters") or [])[:3]:
        a.get("/api/spc", params={"parameter": p})
    return ids["run_id"][0]  # the run diagnosed


def collect(tmp_path, mes: MesCapture) -> tuple[Answers, dict, LiveStation]:
    from web.mes_outbox import OutboxConfig

    outbox = OutboxConfig(url=mes.url, base_delay_s=0.2, max_delay_s=1.0, poll_s=0.3, station_name="test-station")
    ls = LiveStation(tmp_path, n_serial=2, n_can=1, speed=SPEED, fixture=False, operator_hands=True, outbox=outbox)
    ls.__enter__()
    client = httpx.Client(base_url=ls.url, timeout=120)
    from web.views import batch_view

    a = Answers(client, lambda bid: batch_view(ls.call(ls.station.batch_status, bid), bid))
    for t in ("/api/health", "/api/slots", "/api/profiles", "/api/batches"):
        a.get(t)
    t0 = time.monotonic()
    main = run_batch_to_end(a, "fast-thermal-verified")
    t_batch = time.monotonic() - t0
    # the daemon's own status of the ended batch, before the next one ends: from then on the daemon
    # holds only its last ended batch, and the API reads older ones from the database
    main_status = a.station_status(main)
    aborted = abort_a_batch(a)
    ls.flush_db()
    stored = store_records(ls.station.db)
    wait_for(lambda: any(n >= 2 for n in mes.tries.values()), 30, what="a webhook retried and accepted")
    diagnosed = sweep(a, a.client.get("/openapi.json").json(), [main, aborted], stored)
    a.raw += [main_status, a.station_status(aborted)]
    return a, {"batch_s": t_batch, "main": main, "aborted": aborted, "diagnosed": diagnosed, **stored}, ls
