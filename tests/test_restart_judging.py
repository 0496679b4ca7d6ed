"""Issue 35: runs of a profile with no analysis are never judged, also at a restart.

The restart path read the profiles by a name the Station does not have and judged every run a
killed daemon left as a thermal profile's: a validation run went to the MES as `error` and the
first-pass yield dropped. Here:

- `station serve` (a real process, the boards of a SimStation in this process outliving it like
  hardware) is SIGKILLed inside a validation, a fast-thermal and a fast-thermal-verified batch in
  turn; each next `serve` start (and a last restart as `serve` does it) judges what the kill left.
  Only the analysable runs are judged (error, "resumable"); the validation runs keep no verdict,
  and the MES feed (GET /api/results, result_seq) and GET /api/yield are exact to the record;
- every built-in profile, a site profile and a profile the station no longer has but the batch's
  stored config does, on a real SQLite file: judged exactly when the profile has an analysis;
- a database error reading one run's attempt does not stop the other runs' verdicts;
- the VerdictContext refuses a part of the wrong shape where the Station builds it.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.exc import OperationalError

from contracts.events import DutVerdict, EventBus
from contracts.trace import Trace
from db.database import Database
from db.models import Batch, DutRun, VerdictHistoryRow
from drivers.sim.station_sim import SimStation
from cli.commands.demo import sim_config
from station.config import parse_config
from station.daemon.storage import open_database
from station.daemon.supervisor import Station
from station.decisions.moment import judge_interrupted_runs
from station.decisions.verdict_context import VerdictContext
from station.profiles import BUILTIN_PROFILES, all_profiles
from station.version import software_version
from web.app import create_app
from web.auth import TokenStore
from test_daemon_e2e import _to_toml
from web_support import IdleStation

ROOT = Path(__file__).resolve().parents[1]
SPEED = 20.0  # slow plant: every kill lands in its batch's first steps, long before its end
N_SERIAL, N_CAN = 2, 1
N_DUTS = N_SERIAL + N_CAN
MES_TOKEN = "mes-token-restart-0123"
REASON = "interrupted: station restarted during the batch, DUT incomplete (resumable: station serve --resume)"


def _runs(db: Database, batch_id: int) -> list[DutRun]:
    with db.session() as s:
        return list(s.scalars(select(DutRun).where(DutRun.batch_id == batch_id).order_by(DutRun.id)))


def _running(db: Database, batch_id: int) -> bool:
    """The killed daemon's batch has every run made and streaming (what a crash leaves to judge)."""
    try:
        runs = _runs(db, batch_id)
    except OperationalError:  # the daemon is still creating the file's tables
        return False
    return len(runs) == N_DUTS and all(r.state == "running" for r in runs)


async def _serve_then_kill(toml: Path, db_url: str, profile: str, batch_id: int) -> None:
    """`station serve --start-batch PROFILE` (its start judges what the last kill left), then
    SIGKILL once the new batch's runs stream."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "cli", "serve", "--config", str(toml), "--no-web", "--start-batch", profile,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, env=env, cwd=str(ROOT))
    db = Database(db_url)
    try:
        loop = asyncio.get_running_loop()
        end = loop.time() + 120.0
        while not (Path(db_url[len("sqlite:///"):]).exists() and await asyncio.to_thread(_running, db, batch_id)):
            if proc.returncode is not None or loop.time() > end:
                err = (await proc.stderr.read()).decode()[-3000:]
                raise AssertionError(f"{profile}: batch {batch_id} never streamed (rc {proc.returncode}): {err}")
            await asyncio.sleep(0.2)
        proc.send_signal(signal.SIGKILL)
        await proc.wait()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        db.dispose()


async def _kill_three_batches_then_restart(tmp_path: Path) -> tuple[str, dict, int]:
    db_url = f"sqlite:///{tmp_path / 'station.db'}"
    async with SimStation(n_serial=N_SERIAL, n_can=N_CAN, seed=35, speed=SPEED) as sim:
        cfg_dict = sim_config(sim, speed=SPEED, db_url=db_url)
        toml = tmp_path / "station.toml"
        toml.write_text(_to_toml(cfg_dict))
        for batch_id, profile in enumerate(("validation", "fast-thermal", "fast-thermal-verified"), start=1):
            await _serve_then_kill(toml, db_url, profile, batch_id)
        # the last restart, as `station serve` does it (cli/commands/serve.py)
        cfg = parse_config(cfg_dict, "<restart>")
        db = open_database(cfg.database_url, station=cfg.name)
        interrupted = db.mark_interrupted("station restarted")
        st = Station(cfg, db=db)
        try:
            await st.start()
            judged = st.judge_interrupted(interrupted)
            await st.flush_db()
            assert interrupted == [3]
        finally:
            await st.close()
        assert db.mark_interrupted("station restarted") == []  # a restart after it has nothing left
        db.dispose()
    return db_url, cfg_dict, judged


@pytest.mark.timeout(300)
def test_a_restart_judges_only_the_runs_that_have_an_analysis(tmp_path):
    db_url, cfg_dict, judged = asyncio.run(_kill_three_batches_then_restart(tmp_path))
    assert judged == N_DUTS  # the last restart: the fast-thermal-verified runs, nothing else
    db = Database(db_url)
    validation, thermal, verified = (_runs(db, b) for b in (1, 2, 3))
    assert all(r.state == "interrupted" for r in validation + thermal + verified)
    # validation measures nothing for a verdict: no verdict, no MES record, no attempt in the yield
    assert [(r.verdict, r.result_seq) for r in validation] == [(None, None)] * N_DUTS
    for r in thermal + verified:
        assert (r.verdict, r.verdict_reason) == ("error", REASON), (r.id, r.verdict, r.verdict_reason)
    with db.session() as s:
        history = s.execute(select(VerdictHistoryRow.run_id, VerdictHistoryRow.result_seq)
                            .order_by(VerdictHistoryRow.id)).all()
    # one record per judged run, numbered in the order the restarts judged them
    assert history == [(r.id, k + 1) for k, r in enumerate(thermal + verified)]
    # every run the daemon made says what measured it (the plate turned by the fixture)
    for r in validation + thermal + verified:
        assert (r.software_version, r.holder) == (software_version(), "fixture")
        assert r.firmware_version == ("sim-1.0" if r.slot.startswith("s") else None)  # CAN identity: none

    cfg = parse_config(cfg_dict, "<restart>")
    app = create_app(IdleStation(db, cfg), tokens=TokenStore([(MES_TOKEN, "mes", "mes")]), outbox=False)
    auth = {"Authorization": f"Bearer {MES_TOKEN}"}
    with TestClient(app) as c:
        feed = c.get("/api/results", params={"since": "0"}, headers=auth)
        assert feed.status_code == 200, feed.text
        records = feed.json()["results"]
        assert [(x["id"], x["run_id"], x["profile"], x["verdict"], x["revision"], x["supersedes"]) for x in records] == [
            (k + 1, r.id, "fast-thermal" if r.batch_id == 2 else "fast-thermal-verified", "error", 1, None)
            for k, r in enumerate(thermal + verified)]
        assert all(x["attempt"] == r.attempt for x, r in zip(records, thermal + verified))
        assert [r.attempt for r in thermal] == [2] * N_DUTS and [r.attempt for r in verified] == [3] * N_DUTS
        assert feed.json()["next"] == str(2 * N_DUTS)
        y = c.get("/api/yield", headers=auth)
        assert y.status_code == 200, y.text
        assert y.json() == {"batch_id": None, "duts": N_DUTS, "attempts": 2 * N_DUTS, "retested": N_DUTS,
                            "first_pass": 0, "final_pass": 0, "first_pass_yield": 0.0, "final_yield": 0.0}
        y1 = c.get("/api/yield", params={"batch_id": 1}, headers=auth).json()
        assert (y1["duts"], y1["attempts"]) == (N_DUTS, 2 * N_DUTS)  # its DUTs: their two judged attempts
    db.dispose()


# ---- every profile, on a real SQLite file, without hardware ---------------------------------------
SITE = {"slots": [{"name": "s1", "serial": "/dev/null"}, {"name": "s2", "serial": "/dev/zero"}],
        "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1},
        "profiles": {
            "site-check": {"analysis": "none", "steps": [{"name": "P", "position": "P", "require": "static", "dwell_s": 60.0, "timeout_s": 600.0}]},
            "site-thermal": {"analysis": "thermal", "steps": [{"name": "P", "position": "P", "require": "static", "dwell_s": 60.0, "timeout_s": 600.0}]}}}


def _killed_batch(db: Database, profile: str, snapshot: dict, n: int = 2) -> int:
    """A batch as a killed daemon leaves it (running, its runs running), marked at the next start."""
    bid = db.create_batch(profile, "op", snapshot, state="running")
    for k in range(n):
        db.create_run(bid, f"s{k + 1}", f"{profile.upper()}-{bid}-{k}", "LIS3DSH", {"sensor": "LIS3DSH"}, state="running")
    return bid


def _context(db, cfg, bus=None) -> VerdictContext:
    return VerdictContext(db=db, bus=bus or EventBus(), product_for=cfg.product_for, profiles=all_profiles(cfg))


def _verdicts(q) -> list[DutVerdict]:
    out = []
    while not q.empty():
        ev = q.get_nowait()
        if isinstance(ev, DutVerdict):
            out.append(ev)
    return out


@pytest.mark.parametrize("profile", [*BUILTIN_PROFILES, "site-check", "site-thermal"])
def test_every_profile_is_judged_at_a_restart_exactly_when_it_has_an_analysis(tmp_path, profile):
    cfg = parse_config(SITE, "<site>")
    db = open_database(f"sqlite:///{tmp_path / 'station.db'}")
    bid = _killed_batch(db, profile, cfg.snapshot())
    assert db.mark_interrupted() == [bid]
    bus = EventBus()
    q = bus.subscribe()
    analysable = all_profiles(cfg)[profile].analysis != "none"
    assert judge_interrupted_runs(_context(db, cfg, bus), [bid]) == (2 if analysable else 0)
    evs = _verdicts(q)
    assert len(evs) == (2 if analysable else 0)
    assert all(e.verdict["verdict"] == "error" and e.verdict["reason"] == REASON and e.verdict["attempt"] == 1
               for e in evs)
    db.dispose()


def test_a_profile_gone_from_the_config_is_read_from_the_batch_s_stored_config(tmp_path, caplog):
    old = parse_config(SITE, "<site>")
    now = parse_config({k: v for k, v in SITE.items() if k != "profiles"}, "<site, profiles removed>")
    db = open_database(f"sqlite:///{tmp_path / 'station.db'}")
    check = _killed_batch(db, "site-check", old.snapshot())
    thermal = _killed_batch(db, "site-thermal", old.snapshot())
    unknown = _killed_batch(db, "site-lost", {})  # neither the station nor the stored config knows it
    assert db.mark_interrupted() == [check, thermal, unknown]
    bus = EventBus()
    q = bus.subscribe()
    with caplog.at_level(logging.WARNING, logger="station.decisions.moment"):
        assert judge_interrupted_runs(_context(db, now, bus), [check, thermal, unknown]) == 2
    assert {e.batch_id for e in _verdicts(q)} == {thermal}
    assert "profile 'site-lost' unknown" in caplog.text
    db.dispose()


class _FlakyAttempts:
    """A database whose attempt read fails for one run (a lock timeout, a lost connection)."""

    def __init__(self, db: Database, bad_run: int):
        self._db, self.bad_run = db, bad_run

    def run_attempt(self, run_id: int) -> int:
        if run_id == self.bad_run:
            raise OperationalError("SELECT attempt", {}, Exception("database is locked"))
        return self._db.run_attempt(run_id)

    def resume_point(self, batch_id: int):
        return self._db.resume_point(batch_id)

    def batch_trace(self, batch_id: int):
        return self._db.batch_trace(batch_id)

    def unjudged_runs(self, exclude_batches: list[int]) -> dict[int, list[int]]:
        return self._db.unjudged_runs(exclude_batches)


def test_a_database_error_on_one_attempt_does_not_stop_the_other_verdicts(tmp_path, caplog):
    cfg = parse_config(SITE, "<site>")
    db = open_database(f"sqlite:///{tmp_path / 'station.db'}")
    bid = _killed_batch(db, "fast-thermal", cfg.snapshot(), n=2)
    db.mark_interrupted()
    first, second = (r.run_id for r in db.resume_point(bid).runs)
    bus = EventBus()
    q = bus.subscribe()
    with caplog.at_level(logging.WARNING, logger="station.decisions.moment"):
        assert judge_interrupted_runs(_context(_FlakyAttempts(db, first), cfg, bus), [bid]) == 2
    assert [(e.verdict["run_id"], e.verdict["attempt"], e.verdict["verdict"]) for e in _verdicts(q)] == [
        (first, None, "error"), (second, 1, "error")]
    assert f"run {first}: attempt number not read" in caplog.text
    db.dispose()


def test_the_verdict_context_refuses_a_part_of_the_wrong_shape(tmp_path):
    cfg = parse_config(SITE, "<site>")
    db = open_database(f"sqlite:///{tmp_path / 'station.db'}")
    good = dict(db=db, bus=EventBus(), product_for=cfg.product_for, profiles=all_profiles(cfg))
    VerdictContext(**good)
    for wrong, words in (({"db": object()}, "has no run_attempt, resume_point, batch_trace"),
                         ({"bus": db}, "has no publish"),
                         ({"profiles": list(all_profiles(cfg))}, "a mapping of name to Profile"),
                         ({"profiles": {"x": cfg}}, "not a Profile: x"),
                         ({"product_for": cfg}, "product_for is not callable")):
        with pytest.raises(TypeError, match=words):
            VerdictContext(**{**good, **wrong})
    # the Station builds it from its own parts: the profiles it starts batches with
    st = Station(cfg, db=db)
    assert st.verdicts.profiles is st.profiles_by_name and st.verdicts.db is st.db and st.verdicts.bus is st.bus
    db.dispose()


# ---- a retest after a restart ---------------------------------------------------------------------
@pytest.mark.timeout(120)
async def test_a_retest_after_a_restart_takes_the_stored_batch_s_failed_slots(tmp_path):
    """A batch a killed daemon left is judged at the restart (error, resumable); "Retest failed"
    on it then starts a batch of exactly its judged slots with its profile and trace, from the
    database (the restarted daemon never ran it: this answered 404). A batch with nothing to
    retest, one still running in the database and an unknown one answer as for a live batch."""
    from test_daemon_e2e import daemon

    async with SimStation(n_serial=2, n_can=1, seed=36, speed=SPEED) as sim:
        async with daemon(sim, tmp_path, SPEED) as st:
            db = st.db
            snapshot = {"name": st.config.name}
            killed = db.create_batch("fast-thermal", "Ana", snapshot, state="running",
                                     trace=Trace(work_order="WO-36", lot="L7", labels={"s01": "SIM0001"}))
            for slot, serial in (("s01", "SIM0001"), ("s02", "SIM0002")):
                db.create_run(killed, slot, serial, "LIS3DSH", {"sensor": "LIS3DSH"}, state="running")
            checked = db.create_batch("validation", "Ana", snapshot, state="running")
            db.create_run(checked, "s01", "SIM0001", "LIS3DSH", {"sensor": "LIS3DSH"}, state="running")
            still = db.create_batch("fast-thermal", "Ana", snapshot, state="running")
            assert sorted(db.mark_interrupted("station restarted")) == sorted([killed, checked, still])
            assert st.judge_interrupted([killed, checked]) == 2
            await st.flush_db()
            with db.session() as s:  # a batch another process still runs: stored as running
                s.get(Batch, still).state = "running"
                s.commit()

            with pytest.raises(ValueError, match="no slot that ended error, fail or marginal"):
                st.retest_batch(checked, "Ben")  # validation: nothing judged, nothing to retest
            with pytest.raises(ValueError, match="is running in the database"):
                st.retest_batch(still, "Ben")
            with pytest.raises(KeyError):
                st.retest_batch(9999, "Ben")
            new_id = st.retest_batch(killed, "Ben", by="pytest")
            status = st.batch_status(new_id)
            assert sorted(s["slot"] for s in status["slots"]) == ["s01", "s02"]
            assert status["profile"] == "fast-thermal" and status["operator"] == "Ben"
            t = db.batch_trace(new_id)
            assert (t.work_order, t.lot, t.labels) == ("WO-36", "L7", {"s01": "SIM0001"})
            st.abort(new_id, "test over", by="pytest")
            await st.wait_batch(new_id, timeout_s=60)
