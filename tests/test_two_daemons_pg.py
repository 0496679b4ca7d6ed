"""Two WHOLE station daemons (tests/two_daemon_child.py: simulated boards + the real Station with
its DbWriter) on one fresh PostgreSQL database, started at the same moment with boards carrying the
SAME new serials, while an MES client follows `next` of GET /api/results over real HTTP the whole
time. Every batch finishes, each serial has one dut row and attempts 1 and 2, no run creation
collides (insert-or-get by the database: no retry needed), and every MES record (a run's final
verdict) is delivered exactly once by idempotency key.

With the old select-then-insert DUT upsert put back, this test fails: one daemon's create_run hits
UniqueViolation uq_dut_serial (retried: collision_retries > 0; without the retry, the slot faults
and its batch does not finish clean)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import httpx
import pytest
from sqlalchemy import select

from db import Database
from db.models import Dut, DutRun, VerdictHistoryRow
from db_helpers import pg_database, pg_reachable
from test_multi_station import MES_TOKEN, _Api

pytestmark = [pytest.mark.postgres, pytest.mark.skipif(not pg_reachable(), reason="PostgreSQL not reachable")]

ROOT = Path(__file__).resolve().parents[1]
CHILD = ROOT / "tests" / "two_daemon_child.py"
N_SERIAL = 3
SPEED = 300.0
PAGE = 2  # small pages: the client really follows `next` across pages


class MesClient:
    """Follows `next` from 0, for ever: never restarts, never skips; counts rows read."""

    def __init__(self, client: httpx.Client) -> None:
        self.client = client
        self.cursor = "0"
        self.records: list[dict] = []
        self.polls = 0

    def poll(self) -> None:
        while True:
            self.polls += 1
            r = self.client.get("/api/results", params={"since": self.cursor, "limit": PAGE})
            assert r.status_code == 200, r.text
            page = r.json()
            self.records += page["results"]
            assert page["next"] is not None
            self.cursor = page["next"]
            if len(page["results"]) < PAGE:
                return


def _start(url: str, name: str, seed: int, rendezvous: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [os.environ.get("PYTHONPATH"), str(ROOT)])),
               PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, str(CHILD), url, name, str(seed), str(N_SERIAL), str(SPEED), "TWIN",
                             str(rendezvous)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=ROOT)


@pytest.mark.timeout(300)
def test_two_daemons_same_new_serials_one_postgresql(tmp_path):
    t_start = time.monotonic()
    with pg_database() as url:
        db = Database(url, station="mes-side")
        db.upgrade()  # the fresh database at head; the daemons' own upgrade is then a no-op
        daemons: list[subprocess.Popen] = []
        try:
            with _Api(db) as api, httpx.Client(base_url=api.url, timeout=30,
                                               headers={"Authorization": f"Bearer {MES_TOKEN}"}) as http:
                mes = MesClient(http)
                daemons = [_start(url, name, seed, tmp_path) for name, seed in (("line-A", 11), ("line-B", 12))]
                for d in daemons:
                    line = d.stdout.readline().strip()
                    assert line == "READY", d.stderr.read()
                for d in daemons:  # both batches start at the same moment
                    d.stdin.write("go\n")
                    d.stdin.flush()
                while any(d.poll() is None for d in daemons):
                    mes.poll()
                    time.sleep(0.1)
                mes.poll()  # what committed after the last in-flight poll
                outs = [d.communicate(timeout=60) for d in daemons]
        finally:
            for d in daemons:
                if d.poll() is None:
                    d.kill()
            with db.session() as s:
                duts = Counter(s.scalars(select(Dut.serial)))
                runs = s.execute(select(DutRun.id, DutRun.station, Dut.serial, DutRun.attempt, DutRun.verdict)
                                 .join(Dut, Dut.id == DutRun.dut_id)).all()
                records = s.execute(select(VerdictHistoryRow.run_id, VerdictHistoryRow.result_seq)).all()
            db.dispose()

    for d, (out, err) in zip(daemons, outs):
        assert d.returncode == 0, err[-3000:]
    summaries = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    stderr = "\n".join(err for _, err in outs)
    keys = [r["idempotency_key"] for r in mes.records]
    expected_keys = {f"result:{run_id}:{seq}" for run_id, seq in records if seq is not None}
    attempts: dict[str, list[int]] = defaultdict(list)
    for _, _, serial, attempt, _ in runs:
        attempts[serial].append(attempt)
    wall_s = time.monotonic() - t_start
    print(f"\ntwo daemons, {N_SERIAL} boards each with the same new serials, x{SPEED:g}: batches "
          f"{[(s['station'], s['state'], s['wall_s']) for s in summaries]}, collision retries "
          f"{[s['collision_retries'] for s in summaries]}, {len(runs)} runs of {len(duts)} duts, attempts "
          f"{dict(attempts)}, {len(mes.records)} MES records read in {mes.polls} polls "
          f"({len(set(keys))} distinct keys, {len(expected_keys)} stored), {wall_s:.1f} s wall")

    for s in summaries:
        assert s["state"] == "finished" and not s["error"], s
        assert all(sl["state"] == "done" for sl in s["slots"]), s["slots"]
        assert s["writer"]["dropped_events"] == 0 and s["writer"]["storage_failures"] == 0
        assert s["collision_retries"] == 0, "a run creation collided: DUT insert-or-get not by the database"
    assert "UniqueViolation" not in stderr and "Traceback" not in stderr, stderr[-3000:]
    serials = {f"TWIN{i + 1:04d}" for i in range(N_SERIAL)}
    assert duts == Counter({s: 1 for s in serials})  # one row per serial, shared by both daemons
    assert {k: sorted(v) for k, v in attempts.items()} == {s: [1, 2] for s in serials}
    assert {st for _, st, _, _, _ in runs} == {"line-A", "line-B"}
    assert all(v is not None for *_, v in runs)  # every run judged at its end
    # the MES: every final verdict record exactly once, in cursor order, one per run here
    assert len(keys) == len(set(keys)) == len(expected_keys) == 2 * N_SERIAL
    assert set(keys) == expected_keys
    ids = [r["id"] for r in mes.records]
    assert ids == sorted(ids)
    assert all(r["revision"] == 1 and r["supersedes"] is None for r in mes.records)
    assert sorted(r["run_id"] for r in mes.records) == sorted(run_id for run_id, *_ in runs)
    assert wall_s < 120
