"""A line that survives its database (issue 37): two whole stations (tests/outage_station_child.py:
simulated boards, the real Station, writer, journal and web API) on one real PostgreSQL reached
through a proxy the test makes blink (tests/pg_proxy.py), while an MES client follows `next` of
GET /api/results on station A and a prober asks both stations' /api/health every 0.25 s.

1. batch 1 on both; mid-batch the server "restarts" (every connection cut, new ones refused for
   RESTART_S): the batches finish and are judged while the database is away, their records wait
   in each station's journal (health says so, with the count), a new batch is refused with the
   reason; when the server is back the journals are forwarded;
2. batch 2 on both; mid-batch the server hangs for HANG_S (connections open, nobody answers, as
   SIGSTOP): the batches finish and are judged again, health says "not answering since N s";
   when the server answers, the hung commit goes through and the rest is forwarded.

Then, from the database itself: every run has exactly one final verdict (one verdict_history row,
a result_seq), every sample and segment the stations counted is stored once, the MES read every
record exactly once, and no health answer took a second. RESTART_S / HANG_S come from the
environment (OUTAGE_RESTART_S, OUTAGE_HANG_S; 30 and 70 by default): the closing note's 10-minute
outage is OUTAGE_RESTART_S=600."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from db import Database
from db.models import DutRun, SampleChunk, SegmentRow, VerdictHistoryRow
from db_helpers import pg_database, pg_reachable
from pg_proxy import PgProxy
from web_support import free_port

pytestmark = [pytest.mark.postgres, pytest.mark.skipif(not pg_reachable(), reason="PostgreSQL not reachable")]

ROOT = Path(__file__).resolve().parents[1]
CHILD = ROOT / "tests" / "outage_station_child.py"
RESTART_S = float(os.environ.get("OUTAGE_RESTART_S", "30"))
HANG_S = float(os.environ.get("OUTAGE_HANG_S", "70"))
SPEED = 600.0
N_SERIAL = 3
MES = {"Authorization": "Bearer mes-token-0123456789"}
OPS = {"Authorization": "Bearer line-token-0123456789"}
HEALTH_BOUND_S = 1.0


class Station:
    def __init__(self, url: str, name: str, seed: int, journal: Path) -> None:
        self.name = name
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, str(CHILD), url, name, str(seed), str(N_SERIAL), str(SPEED),
                                      str(self.port), str(journal), name[-1] + "OUT"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env=env, cwd=ROOT)
        assert self.proc.stdout.readline().strip() == "READY", self.proc.stderr.read()[-3000:]

    def go(self) -> dict:
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def status(self, bid: int) -> dict:
        r = httpx.get(f"{self.base}/api/batches/{bid}", headers=OPS, timeout=5)
        assert r.status_code == 200, r.text
        return r.json()

    def health(self) -> dict:
        return httpx.get(f"{self.base}/api/health", timeout=5).json()

    def finish(self) -> tuple[dict, str]:
        out, err = self.proc.communicate(input="", timeout=300)
        assert self.proc.returncode == 0, err[-3000:]
        return json.loads(out.strip().splitlines()[-1]), err


class Prober(threading.Thread):
    """/api/health of every station every 0.25 s; keeps the slowest answer and what was said."""

    def __init__(self, stations: list[Station]) -> None:
        super().__init__(daemon=True)
        self.stations = stations
        self.worst_s = 0.0
        self.failures: list[str] = []
        self.said: list[tuple[str, str, int]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        with httpx.Client(timeout=5) as c:
            while not self.stop.is_set():
                for st in self.stations:
                    t0 = time.monotonic()
                    try:
                        r = c.get(f"{st.base}/api/health")
                        body = r.json()
                        self.said.append((st.name, str(body.get("db")), int((body.get("forwarding") or {}).get("events", 0))))
                    except Exception as exc:  # noqa: BLE001 - counted as a failure
                        self.failures.append(f"{st.name}: {exc!r}")
                    self.worst_s = max(self.worst_s, time.monotonic() - t0)
                time.sleep(0.25)


class Mes(threading.Thread):
    """Follows `next` of GET /api/results on one station for ever; a 503 (database away) is
    retried, anything else that is not 200 is a failure."""

    def __init__(self, st: Station) -> None:
        super().__init__(daemon=True)
        self.st = st
        self.cursor = "0"
        self.records: list[dict] = []
        self.unavailable = 0
        self.failures: list[str] = []
        self.stop = threading.Event()

    def poll(self, c: httpx.Client) -> None:
        while True:
            r = c.get(f"{self.st.base}/api/results", params={"since": self.cursor, "limit": 5})
            if r.status_code == 503:
                self.unavailable += 1
                return
            if r.status_code != 200:
                self.failures.append(f"{r.status_code} {r.text[:200]}")
                return
            page = r.json()
            self.records += page["results"]
            self.cursor = page["next"]
            if len(page["results"]) < 5:
                return

    def run(self) -> None:
        with httpx.Client(timeout=20, headers=MES) as c:
            while not self.stop.is_set():
                try:
                    self.poll(c)
                except httpx.HTTPError as exc:
                    self.failures.append(repr(exc))
                time.sleep(0.5)
            self.poll(c)


def wait(cond, what: str, timeout_s: float, said=lambda: "") -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out: {what} {said()}"
        time.sleep(0.2)


def ended(st: Station, bid: int) -> bool:
    return st.status(bid)["state"] in ("finished", "failed", "aborted", "interrupted")


def outage_round(stations: list[Station], bids: list[int], fault, heal, down_s: float, words: str) -> dict:
    """Mid-batch: fault(); the batches end and are judged while the database is away; a new batch
    is refused with the reason; after down_s, heal() and every journal is forwarded."""
    wait(lambda: all(st.status(b)["step_index"] >= 1 for st, b in zip(stations, bids)), "batches mid-way", 60)
    t_fault = time.monotonic()
    fault()
    wait(lambda: all(ended(st, b) for st, b in zip(stations, bids)), "batches end during the outage", down_s)
    seen: dict = {}
    for st, b in zip(stations, bids):
        status = st.status(b)
        seen[st.name] = status
        assert status["state"] == "finished", (status["state"], status["error"])
        assert all(s["state"] == "done" and s["decision"] for s in status["slots"]), status["slots"]
    wait(lambda: all(words in str(st.health()["db"]) for st in stations), f"health says {words!r}", 15,
         lambda: [st.health()["db"] for st in stations])
    health = {st.name: st.health() for st in stations}
    assert all(h["forwarding"]["events"] > 0 for h in health.values()), health
    refused = stations[0].go()
    assert "refused" in refused and "no new batch can start" in refused["refused"], refused
    remaining = down_s - (time.monotonic() - t_fault)
    assert remaining > 0, "the batches outlasted the outage: nothing was tested"
    time.sleep(remaining)
    heal()
    wait(lambda: all(st.health()["db"] == "ok" for st in stations), "every journal forwarded", 120,
         lambda: [st.health() for st in stations])
    return {"health_during": health, "refused": refused["refused"]}


@pytest.mark.timeout(900)
def test_two_stations_through_a_restart_and_a_hang_every_dut_one_verdict(tmp_path):
    with pg_database() as direct_url:
        db = Database(direct_url, station="mes-side")
        db.upgrade()
        proxy = PgProxy()
        url = proxy.url(direct_url.rsplit("/", 1)[1])
        stations: list[Station] = []
        try:
            stations = [Station(url, f"line-{c}", seed, tmp_path / f"{c}.journal")
                        for c, seed in (("A", 21), ("B", 22))]
            prober, mes = Prober(stations), Mes(stations[0])
            prober.start()
            mes.start()
            bids1 = [st.go()["started"] for st in stations]
            r1 = outage_round(stations, bids1, lambda: proxy.restart(RESTART_S), lambda: None, RESTART_S,
                              "database unreachable")
            bids2 = [st.go()["started"] for st in stations]
            r2 = outage_round(stations, bids2, proxy.hang, proxy.resume, HANG_S, "database not answering")
            time.sleep(2)
            mes.stop.set()
            mes.join(60)
            prober.stop.set()
            prober.join(10)
            results = [st.finish() for st in stations]
        finally:
            for st in stations:
                if st.proc.poll() is None:
                    st.proc.kill()
            proxy.close()
        with db.session() as s:
            runs = s.execute(select(DutRun.id, DutRun.station, DutRun.batch_id, DutRun.verdict, DutRun.result_seq,
                                    DutRun.n_samples)).all()
            history = Counter(s.scalars(select(VerdictHistoryRow.run_id)))
            samples = dict(s.execute(select(SampleChunk.run_id, func.sum(SampleChunk.n)).group_by(SampleChunk.run_id)).all())
            segments = dict(s.execute(select(SegmentRow.run_id, func.count(SegmentRow.id)).group_by(SegmentRow.run_id)).all())
            keys = {f"result:{r}:{q}" for r, q in s.execute(select(VerdictHistoryRow.run_id, VerdictHistoryRow.result_seq))}
        db.dispose()

    summaries = {out["station"]: out for out, _ in results}
    counted = {(sl["run_id"]): sl for out in summaries.values() for b in out["batches"] for sl in b["slots"]}
    print(f"\noutage: restart {RESTART_S:g} s, hang {HANG_S:g} s; {len(runs)} runs; health worst "
          f"{prober.worst_s * 1000:.0f} ms over {len(prober.said)} answers; MES {len(mes.records)} records, "
          f"{mes.unavailable} answers 503 during the outages; during the restart {r1['health_during']}; "
          f"during the hang {r2['health_during']}; refused: {r1['refused']!r} / {r2['refused']!r}; writers "
          f"{ {k: v['writer'] for k, v in summaries.items()} }")
    assert len(runs) == 2 * 2 * N_SERIAL and len(counted) == len(runs)
    for run_id, station, bid, verdict, seq, _ in runs:
        assert verdict is not None and seq is not None, (run_id, station, bid)
        assert history[run_id] == 1, f"run {run_id}: {history[run_id]} verdict records"
        assert samples.get(run_id) == counted[run_id]["samples"], (run_id, samples.get(run_id), counted[run_id])
        assert segments.get(run_id) == counted[run_id]["segments"], (run_id, segments.get(run_id))
        assert verdict == counted[run_id]["verdict"]
    for out in summaries.values():
        assert out["writer"]["dropped_events"] == 0 and out["writer"]["abandoned_events"] == 0, out["writer"]
        assert out["writer"]["journaled_events"] > 0 and out["writer"]["forwarded_events"] > 0, out["writer"]
    got = [r["idempotency_key"] for r in mes.records]
    assert not mes.failures, mes.failures[:5]
    assert len(got) == len(set(got)) == len(keys) and set(got) == keys  # every record once
    assert all(r["revision"] == 1 and r["supersedes"] is None for r in mes.records)
    assert mes.unavailable > 0  # the MES did meet the outage
    assert not prober.failures, prober.failures[:5]
    assert prober.worst_s < HEALTH_BOUND_S, prober.worst_s
