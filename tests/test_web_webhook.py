"""MES webhook outbox against a real HTTP receiver on 127.0.0.1 that fails the first deliveries.

Phase 1: a station runs a batch while the MES is down (HTTP 500s, connections dropped without a
reply, and one record stored whose reply is lost). Every finished DUT's result waits in the db
outbox with its failed attempts counted; then the station stops (the worker with it).
Phase 2: a new station process on the same database file, more results arrive, the MES comes back
after two more failures. Every result reaches the MES exactly once by idempotency key: one record
per key, one acknowledged delivery per key, the key in the header and the payload alike.
"""

from __future__ import annotations

import json
import threading
from collections import Counter
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from web.mes_outbox import OutboxConfig
from web_support import LiveStation, auth, seed_results, wait_for


class MesReceiver:
    """A tiny MES: stores records by idempotency key; `plan` scripts the next replies."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.plan: list[str] = []     # actions for the next requests: "500", "drop", "lost", "ok"
        self.default = "ok"
        self.attempts: list[tuple[str, str]] = []   # (key, action) per request
        self.records: dict[str, dict] = {}          # the MES's store
        self.acked: Counter = Counter()             # key -> 200 replies sent
        self.mismatches: list[str] = []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # quiet
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
                key = self.headers.get("Idempotency-Key") or ""
                payload = json.loads(body)
                with receiver.lock:
                    action = receiver.plan.pop(0) if receiver.plan else receiver.default
                    receiver.attempts.append((key, action))
                    if payload.get("idempotency_key") != key:
                        receiver.mismatches.append(f"header {key!r} != payload {payload.get('idempotency_key')!r}")
                    if action in ("ok", "lost"):
                        old = receiver.records.setdefault(key, payload)
                        if old != payload:
                            receiver.mismatches.append(f"{key}: a second, different record")
                    if action == "ok":
                        receiver.acked[key] += 1
                if action in ("drop", "lost"):  # no reply at all: the connection just closes
                    self.close_connection = True
                    return
                code = 200 if action == "ok" else 500
                out = json.dumps({"stored": action == "ok"}).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(out)))
                self.end_headers()
                self.wfile.write(out)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/mes/results"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> "MesReceiver":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()

    def set(self, plan: list[str], default: str) -> None:
        with self.lock:
            self.plan, self.default = list(plan), default

    def actions(self) -> Counter:
        with self.lock:
            return Counter(a for _, a in self.attempts)


def outbox(client) -> list[dict]:
    r = client.get("/api/outbox", headers=auth("admin"))
    assert r.status_code == 200
    return r.json()


def test_every_result_reaches_the_mes_exactly_once_across_a_restart(tmp_path):
    cfg = OutboxConfig(url="", timeout_s=2.0, base_delay_s=0.1, max_delay_s=0.4, poll_s=0.2, station_name="test-station")
    with MesReceiver() as mes:
        cfg.url = mes.url
        # --- phase 1: the MES is down; a batch finishes; the station stops -------------------------
        mes.set(["drop", "lost", "500", "drop"], default="500")
        with LiveStation(tmp_path, n_serial=2, n_can=1, speed=400.0, fixture=True, outbox=cfg) as live:
            with httpx.Client(base_url=live.url, timeout=20) as c:
                r = c.post("/api/batches", json={"profile": "fast-thermal", "operator": "mes-test"}, headers=auth("operator"))
                assert r.status_code == 201, r.text
                bid = r.json()["id"]
                wait_for(lambda: c.get(f"/api/batches/{bid}", headers=auth("operator")).json()["state"] == "finished",
                         120, interval_s=0.3, what="batch end")
                live.flush_db()
                first = wait_for(lambda: (o := outbox(c)) and len(o) == 3 and all(e["attempts"] >= 2 for e in o) and o,
                                 30, what="3 queued results, each tried twice")
                assert all(e["state"] == "pending" for e in first)
                assert all(e["last_error"] for e in first)
                batch_keys = {e["idempotency_key"] for e in first}
        acts = mes.actions()
        assert acts["ok"] == 0 and acts["500"] >= 3 and acts["drop"] >= 2 and acts["lost"] == 1
        assert len(mes.records) == 1  # the MES stored one whose reply was lost; the station cannot know
        assert set(mes.records) <= batch_keys

        # --- phase 2: a new station process on the same database; the MES comes back ---------------
        mes.set(["500", "drop"], default="ok")
        with LiveStation(tmp_path, n_serial=2, n_can=1, speed=400.0, fixture=True, outbox=cfg) as live:
            with httpx.Client(base_url=live.url, timeout=20) as c:
                seeded = seed_results(live.station.db, 4, serial_prefix="MES", seed=5)
                done = wait_for(lambda: (o := outbox(c)) and len(o) == 7 and all(e["state"] == "delivered" for e in o) and o,
                                60, what="every result delivered")
                feed = c.get("/api/results", params={"limit": 100}, headers=auth("mes")).json()["results"]
                # a little longer: nothing is sent again once acknowledged
                n_attempts = len(mes.attempts)
                import time

                time.sleep(1.5)
                assert len(mes.attempts) == n_attempts

    keys = {it["idempotency_key"] for it in feed}
    assert len(feed) == 7 and len(keys) == 7
    assert {e["idempotency_key"] for e in done} == keys
    assert batch_keys < keys
    # exactly once by idempotency key: one record each, one acknowledged delivery each
    assert set(mes.records) == keys
    assert all(mes.acked[k] == 1 for k in keys), mes.acked
    assert not mes.mismatches, mes.mismatches
    # the record is the result: serial, run, and TDB/TDSF per axis as the results feed gives them
    for it in feed:
        rec = mes.records[it["idempotency_key"]]
        assert rec["serial"] == it["serial"] and rec["run_id"] == it["run_id"] and rec["station"] == "test-station"
        for ax in "xyz":
            assert rec["thermal"][ax]["tdb_mg_per_c"] == pytest.approx(it["thermal"][ax]["tdb_mg_per_c"], rel=1e-12)
            assert rec["thermal"][ax]["tdsf_ppm_per_c"] == pytest.approx(it["thermal"][ax]["tdsf_ppm_per_c"], rel=1e-12)
    assert {it["serial"] for it in feed} >= set(seeded)
    # the batch's results were retried across the restart: more than one attempt each
    tries = Counter(k for k, _ in mes.attempts)
    assert all(tries[k] >= 3 for k in batch_keys), tries
