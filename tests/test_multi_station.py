"""Many stations, one database (issue 13): two station processes write results into one PostgreSQL
database at the same time while an MES client pages `GET /api/results?since=` over real HTTP the
whole time. Every result must arrive exactly once, with no result_seq collision, and the cursor
must never step over a result that commits late (result_seq is taken in commit order)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest
from sqlalchemy import select

from db import Database, DbWriter
from db import repository as repo
from db.models import DutRun
from db.writer import take_result_seq
from contracts.events import DutVerdict
from db_helpers import pg_database, pg_reachable
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

pytestmark = [pytest.mark.postgres, pytest.mark.skipif(not pg_reachable(), reason="PostgreSQL not reachable")]

MES_TOKEN = "mes-token-multi-station"
CHILD = Path(__file__).resolve().parent / "multi_station_child.py"


class _Api:
    """The web app on a free loopback port, in a thread with its own loop (no daemon needed: the
    results feed reads the database), started as the daemon starts its own (web_support)."""

    def __init__(self, db: Database) -> None:
        self.app = create_app(SimpleNamespace(config=None, bus=None, db=db), repo=DbRepository(db),
                              tokens=TokenStore([(MES_TOKEN, "mes", "mes-client")]), outbox=False)
        self.url = ""
        self._stop = None

    def __enter__(self) -> "_Api":
        self.url, self._stop = serve_in_thread(self.app)
        return self

    def __exit__(self, *exc) -> None:
        self._stop()


def test_counter_gives_commit_order_on_postgresql():
    """A result that takes its number first but commits last holds back the next writer: the
    reader never sees number N+1 while N is still in flight (with a sequence it would, and a
    `since` cursor would step over N for ever)."""
    with pg_database() as url:
        db = Database(url, station="A")
        db.upgrade()
        try:
            conn_a = db.engine.connect()
            tx_a = conn_a.begin()
            a = take_result_seq(conn_a)
            got: dict[str, float] = {}

            def second_station() -> None:
                with db.engine.begin() as conn_b:
                    got["b"] = take_result_seq(conn_b)
                    got["t"] = time.monotonic()

            t = threading.Thread(target=second_station)
            t.start()
            time.sleep(0.5)
            assert "b" not in got, "the second writer took a number while the first was in flight"
            t_commit = time.monotonic()
            tx_a.commit()
            conn_a.close()
            t.join(10)
            assert got["b"] == a + 1 and got["t"] >= t_commit
        finally:
            db.dispose()


def test_two_stations_one_postgresql_mes_gets_every_result_once():
    n_batches, per_batch = 4, 12
    with pg_database() as url:
        db = Database(url, station="mes-side")
        db.upgrade()
        delivered: list[dict] = []
        polls = 0
        try:
            with _Api(db) as api, httpx.Client(base_url=api.url, timeout=30,
                                               headers={"Authorization": f"Bearer {MES_TOKEN}"}) as client:
                children = [
                    subprocess.Popen([sys.executable, str(CHILD), url, name, str(n_batches), str(per_batch), str(seed)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                    for name, seed in (("line-A", 1), ("line-B", 2))
                ]
                cursor = 0

                def poll() -> int:
                    nonlocal cursor, polls
                    n = 0
                    while True:  # follow `next` (limit 7) until a page is not full: the last for now
                        polls += 1
                        r = client.get("/api/results", params={"since": str(cursor), "limit": 7})
                        assert r.status_code == 200, r.text
                        page = r.json()
                        for item in page["results"]:
                            assert item["id"] > cursor  # strictly increasing across pages
                            delivered.append(item)
                            n += 1
                        assert page["next"] == str(page["results"][-1]["id"] if page["results"] else cursor)
                        cursor = int(page["next"])  # never null: the last page's cursor is where to poll from
                        if len(page["results"]) < 7:
                            return n

                while any(c.poll() is None for c in children):
                    poll()
                    time.sleep(0.05)
                poll()  # whatever committed after the last in-flight poll
                only_b = client.get("/api/results", params={"station": "line-B", "limit": 1000}).json()["results"]
                outs = [c.communicate(timeout=60) for c in children]
                for c, (out, err) in zip(children, outs):
                    assert c.returncode == 0, err
                stats = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
        finally:
            with db.engine.connect() as conn:
                stored = conn.execute(select(DutRun.id, DutRun.station, DutRun.result_seq)).all()
            db.dispose()

        expected = 2 * n_batches * per_batch
        run_ids = [d["run_id"] for d in delivered]
        seqs = [d["id"] for d in delivered]
        per_station = {s: sum(1 for d in delivered if d["station"] == s) for s in ("line-A", "line-B")}
        print(f"\ntwo stations, one PostgreSQL: {expected} results written "
              f"({stats[0]['commits']} + {stats[1]['commits']} writer commits), {len(delivered)} delivered "
              f"to the MES in {polls} polls, {len(set(run_ids))} distinct runs, {len(set(seqs))} distinct "
              f"result ids, per station {per_station}, dropped {stats[0]['dropped'] + stats[1]['dropped']}")
        assert all(s["dropped"] == 0 and s["storage_failures"] == 0 for s in stats)  # no result_seq collision
        assert len(stored) == expected and all(seq is not None for _, _, seq in stored)
        assert len({seq for _, _, seq in stored}) == expected
        assert sorted(run_ids) == sorted(r for r, _, _ in stored)  # every result exactly once
        assert len(set(run_ids)) == len(run_ids) == expected
        assert seqs == sorted(seqs) and len(set(seqs)) == expected
        assert per_station == {"line-A": expected // 2, "line-B": expected // 2}
        assert {st for _, st, _ in stored} == {"line-A", "line-B"}
        assert len(only_b) == expected // 2 and {r["station"] for r in only_b} == {"line-B"}
        assert polls > 5  # the client really polled while the stations wrote


def test_sqlite_counter_and_station_names(tmp_path):
    """The same counter on SQLite; a station only marks its own batches interrupted at start."""
    url = f"sqlite:///{tmp_path / 's.db'}"
    a, b = Database(url, station="A"), Database(url, station="B")
    a.upgrade()
    ba, bb = a.create_batch("fast-thermal", "op", {}, state="running"), b.create_batch("fast-thermal", "op", {}, state="running")
    ra, rb = a.create_run(ba, "s1", "SA", "LIS3DSH"), b.create_run(bb, "s1", "SB", "LIS3DSH")
    for db, batch, run, serial in ((a, ba, ra, "SA"), (b, bb, rb, "SB")):  # each station's final verdict
        with DbWriter(db) as w:
            w.bind_run(batch, "s1", run)
            w.submit(DutVerdict(batch, "s1", serial, verdict={"verdict": "pass"}))
    s1, s2 = (repo.run_detail(a, r)["result_seq"] for r in (ra, rb))
    assert (s1, s2) == (1, 2)
    assert [(r["station"], r["id"]) for r in repo.results_since(a, 0)] == [("A", 1), ("B", 2)]
    assert [r["id"] for r in repo.results_since(a, 0, station="B")] == [2]
    assert a.mark_interrupted() == [ba]
    assert repo.batch_detail(b, bb)["state"] == "running" and repo.batch_detail(a, ba)["station"] == "A"
