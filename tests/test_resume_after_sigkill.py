"""Issue 4's crash test: `station serve` runs a fast-thermal batch against a simulated station that
lives in another process; the daemon is SIGKILLed in the middle of the batch, restarted with
`--resume latest`, and the batch finishes as the same runs with correct results. Every segment the
database held before the kill is still there and SQLite's integrity check passes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from sqlalchemy import select

from db.database import Database
from db.models import Batch, DutRun, SegmentRow
from db.repository import batch_detail
from test_daemon_e2e import TDB_TOL_MG_PER_C, TDSF_TOL_PPM_PER_C, _to_toml

ROOT = Path(__file__).resolve().parents[1]
SPEED = 120.0


def _segments(db: Database) -> set[tuple[int, int, float]]:
    with db.session() as s:
        return {tuple(r) for r in s.execute(select(SegmentRow.run_id, SegmentRow.seg_index, SegmentRow.t_end_s))}


def _batch_row(db: Database) -> tuple[str, int | None] | None:
    from sqlalchemy.exc import OperationalError

    try:
        with db.session() as s:
            row = s.execute(select(Batch.state, Batch.last_completed_step).where(Batch.id == 1)).first()
    except OperationalError:  # the daemon created the file and is still migrating it (CI: "no such table")
        return None
    return None if row is None else (row[0], row[1])


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_sigkill_mid_batch_then_resume_finishes_with_correct_results(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    sim_json = tmp_path / "sim.json"
    sim = subprocess.Popen([sys.executable, str(ROOT / "tests" / "sim_station_child.py"), str(sim_json),
                            "--serial", "3", "--can", "1", "--speed", str(SPEED), "--seed", "8"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    daemon = None
    try:
        assert sim.stdout.readline().strip() == "READY", sim.stderr.read()
        spec = json.loads(sim_json.read_text())
        cfg = spec["config"]
        db_url = f"sqlite:///{tmp_path / 'station.db'}"
        cfg["database_url"] = db_url
        toml = tmp_path / "station.toml"
        toml.write_text(_to_toml(cfg))
        serve = [sys.executable, "-m", "cli", "serve", "--config", str(toml), "--no-web"]

        daemon = subprocess.Popen(serve + ["--start-batch", "fast-thermal"], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
        db = Database(db_url)
        # Kill once two steps are complete and the third has logged samples: mid-batch, mid-step.
        deadline = time.monotonic() + 300
        while True:
            assert daemon.poll() is None, daemon.communicate()[1]
            assert time.monotonic() < deadline, "batch never got past step 2"
            row = _batch_row(db) if (tmp_path / "station.db").exists() else None
            # two steps complete AND their segments committed (the writer commits in its own time:
            # on a loaded machine the step's row can be read before the last DUT's segment row)
            if row is not None and row[1] is not None and row[1] >= 1 and len(_segments(db)) >= 8:
                time.sleep(3.0)  # well inside step 2 (N hot), samples streaming
                break
            time.sleep(0.5)
        before = _segments(db)
        with db.session() as s:
            runs_before = sorted(s.scalars(select(DutRun.id)))
        os.kill(daemon.pid, signal.SIGKILL)
        daemon.wait(30)
        assert daemon.returncode == -signal.SIGKILL
        daemon = None
        assert db.sqlite_integrity_check() == "ok"
        after_kill = _segments(db)
        assert before <= after_kill and len(before) >= 8  # 4 DUTs x 2 completed steps at least
        db.dispose()

        out = subprocess.run(serve + ["--resume", "latest", "--once"], capture_output=True, text=True, env=env,
                             cwd=ROOT, timeout=400)
        assert out.returncode == 0, out.stdout + out.stderr
        assert "batch 1 resumed" in out.stdout and "batch 1 finished" in out.stdout, out.stdout

        db = Database(db_url)
        assert db.sqlite_integrity_check() == "ok"
        assert after_kill <= _segments(db)  # nothing committed before the kill was lost
        detail = batch_detail(db, 1)
        assert detail["state"] == "finished" and detail["last_completed_step"] == 3
        assert sorted(r["id"] for r in detail["runs"]) == runs_before  # same runs, resumed, not new ones
        truths = spec["truths"]
        from db.repository import dut_by_serial

        for r in detail["runs"]:
            assert r["state"] == "done", (r["slot"], r["fault_reason"])
            t = truths[r["slot"]]
            dut = dut_by_serial(db, t["serial"])
            for k, a in enumerate("xyz"):
                got = dut["thermal"][a]
                assert abs(got["tdb_mg_per_c"] - t["tdb_mg_per_c"][k]) < TDB_TOL_MG_PER_C, (r["slot"], a, got, t)
                assert abs(got["tdsf_ppm_per_c"] - t["tdsf_ppm_per_c"][k]) < TDSF_TOL_PPM_PER_C, (r["slot"], a, got, t)
        db.dispose()
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
            daemon.wait(10)
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(20)
        except subprocess.TimeoutExpired:
            sim.kill()
