"""Many stations creating runs for the same NEW serials at the same moment (one PostgreSQL, or one
SQLite file): the DUT row is insert-or-get by the database itself (INSERT ... ON CONFLICT DO
NOTHING, db.database.upsert_dut), never a select-then-insert, which two daemons meeting the same
new serial lost with `UniqueViolation uq_dut_serial` (a crashed batch).

What is guaranteed and checked here: no exception; exactly one dut row per serial; every run
created; the attempts of each serial are 1..N without duplicates or gaps (the DUT row is row-locked
by create_run's UPDATE while it counts the earlier attempts, so run creation for one serial is
serialised across connections and processes); and no collision at all (Database.collision_retries
stays 0): the database settles who inserts the row, create_run's retry of a unique collision is
for what else may collide, not the way the DUT row is made.

With the old select-then-insert put back (upsert_dut: `select`, then `s.add(Dut(...))` when none),
every test here fails: on PostgreSQL UniqueViolation uq_dut_serial in several threads (retried,
so collision_retries > 0; without the retry, failed run creations), on SQLite the same.
"""

from __future__ import annotations

import random
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import pytest
from sqlalchemy import func, select

from db import Database
from db.models import Dut, DutRun
from db_helpers import pg_database, pg_reachable

N_THREADS = 16
SERIALS = [f"RACE{i:03d}" for i in range(6)]
ROUNDS = 3  # every thread creates a run for every serial in each round

def _hammer(url: str, station: str, barrier: threading.Barrier | None, seed: int, errors: list) -> None:
    """One 'station': its own Database (engine, connections), a batch, then a run for each serial
    in a shuffled order, all threads released together before every call."""
    db = Database(url, station=station)
    rng = random.Random(seed)
    try:
        for r in range(ROUNDS):
            batch = db.create_batch("fast-thermal", station, {})
            order = list(SERIALS)
            rng.shuffle(order)
            for k, serial in enumerate(order):
                if barrier is not None:
                    barrier.wait(timeout=60)
                try:
                    db.create_run(batch, f"s{k:02d}", serial, "LIS3DSH", {"serial": serial})
                except Exception as exc:  # noqa: BLE001 - the test counts every failure
                    errors.append(f"{station} {serial}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    except threading.BrokenBarrierError:
        errors.append(f"{station}: barrier broken")
    finally:
        if db.collision_retries:
            errors.append(f"{station}: {db.collision_retries} unique collision(s) retried")
        db.dispose()


def _check(url: str, n_creators: int, errors: list) -> dict:
    """One dut per serial, every run, attempts 1..N per serial."""
    db = Database(url)
    try:
        with db.session() as s:
            duts = dict(s.execute(select(Dut.serial, func.count(Dut.id)).group_by(Dut.serial)).all())
            attempts: dict[str, list[int]] = defaultdict(list)
            for serial, attempt in s.execute(select(Dut.serial, DutRun.attempt).join(DutRun, DutRun.dut_id == Dut.id)):
                attempts[serial].append(attempt)
    finally:
        db.dispose()
    n = n_creators * ROUNDS
    assert errors == [], f"{len(errors)} run creations failed, e.g. {errors[:3]}"
    assert duts == {s: 1 for s in SERIALS}
    for serial in SERIALS:
        assert sorted(attempts[serial]) == list(range(1, n + 1)), (serial, sorted(attempts[serial]))
    return {"duts": len(duts), "runs": sum(len(v) for v in attempts.values())}


def _run_threads(url: str, n: int) -> tuple[list, float]:
    errors: list[str] = []
    barrier = threading.Barrier(n)
    threads = [threading.Thread(target=_hammer, args=(url, f"st{i:02d}", barrier, i, errors)) for i in range(n)]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    return errors, time.monotonic() - t0


@pytest.mark.postgres
@pytest.mark.skipif(not pg_reachable(), reason="PostgreSQL not reachable")
def test_same_new_serials_from_many_threads_on_postgresql():
    with pg_database() as url:
        Database(url).upgrade()
        errors, wall_s = _run_threads(url, N_THREADS)
        got = _check(url, N_THREADS, errors)
        print(f"\n{N_THREADS} threads x {ROUNDS} rounds x {len(SERIALS)} new serials on one PostgreSQL: "
              f"{got['runs']} runs, {got['duts']} duts, 0 errors in {wall_s:.1f} s")


CHILD_CODE = """
import sys, threading
sys.path.insert(0, {tests!r}); sys.path.insert(0, {root!r})
from test_db_concurrency import _hammer
errors = []
_hammer({url!r}, {station!r}, None, {seed}, errors)
print("ERRORS", len(errors)); [print(e) for e in errors]
"""


@pytest.mark.postgres
@pytest.mark.skipif(not pg_reachable(), reason="PostgreSQL not reachable")
def test_same_new_serials_from_many_processes_on_postgresql():
    """Whole processes (as two daemons would be), each with its own connections."""
    tests = str(Path(__file__).resolve().parent)
    root = str(Path(tests).parent)
    n = 6
    with pg_database() as url:
        Database(url).upgrade()
        procs = [subprocess.Popen([sys.executable, "-c", CHILD_CODE.format(tests=tests, root=root, url=url,
                                                                             station=f"proc{i}", seed=i)],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(n)]
        errors: list[str] = []
        for p in procs:
            out, err = p.communicate(timeout=180)
            assert p.returncode == 0, err
            lines = out.strip().splitlines()
            errors += lines[lines.index(next(x for x in lines if x.startswith("ERRORS"))) + 1:]
        got = _check(url, n, errors)
        print(f"\n{n} processes x {ROUNDS} rounds x {len(SERIALS)} new serials: {got['runs']} runs, "
              f"{got['duts']} duts, 0 errors")


def test_same_new_serials_from_many_threads_on_sqlite(tmp_path):
    """SQLite serialises writers; the old select-then-insert lost here too (IntegrityError after the
    busy wait); insert-or-get first takes the write lock, then counts."""
    url = f"sqlite:///{tmp_path / 'race.db'}"
    Database(url).upgrade()
    errors, wall_s = _run_threads(url, 8)
    got = _check(url, 8, errors)
    print(f"\n8 threads on one SQLite file: {got['runs']} runs in {wall_s:.1f} s")
