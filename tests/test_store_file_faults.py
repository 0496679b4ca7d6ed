"""The station's SQLite file under faults a plant meets (issue 37), on a real `station serve`
(simulated boards in tests/sim_station_child.py, as real hardware they outlive the daemon):

- the database file deleted (or replaced by another database) mid-batch: /api/health says so within 5 s, a new batch is refused
  (503, with the reason), the batch goes on and ends judged, what the deleted file held is rescued
  beside it and every later event waits in the journal; the restart is refused in one line naming
  the marker and `--new-database`; with the rescued file put back, the restart forwards the journal
  and nothing is missing: every sample the daemon counted, a verdict for every run;
- SIGTERM while another process holds the database's lock: the daemon exits within
  SIGTERM_BOUND_S (docs/design.md), what it could not commit waits in the journal, and after the
  lock is gone a restart stores it: the samples of every run with no gap, one verdict per run.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlalchemy import func, select

from db.database import Database
from db.export import run_samples
from db.models import DutRun, VerdictHistoryRow
from db_helpers import HOLD_LOCK
from test_daemon_e2e import _to_toml
from web_support import free_port

ROOT = Path(__file__).resolve().parents[1]
SPEED = 120.0
SIGTERM_BOUND_S = 10.0
OPS = {"Authorization": "Bearer ops-token-0123456789"}


class Rig:
    """A simulated station (its own process) and `station serve` on a SQLite file in tmp_path."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp = tmp_path
        self.env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        sim_json = tmp_path / "sim.json"
        self.sim = subprocess.Popen([sys.executable, str(ROOT / "tests" / "sim_station_child.py"), str(sim_json),
                                     "--serial", "3", "--can", "0", "--speed", str(SPEED), "--seed", "31"],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=self.env, cwd=ROOT)
        assert self.sim.stdout.readline().strip() == "READY", self.sim.stderr.read()
        cfg = json.loads(sim_json.read_text())["config"]
        self.db_path = tmp_path / "station.db"
        cfg["database_url"] = f"sqlite:///{self.db_path}"
        cfg["tokens"] = [{"name": "ops", "token": OPS["Authorization"].split()[1], "role": "operator"}]
        self.toml = tmp_path / "station.toml"
        self.toml.write_text(_to_toml(cfg))
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.daemon: subprocess.Popen | None = None

    def serve(self, *extra: str) -> subprocess.Popen:
        self.daemon = subprocess.Popen([sys.executable, "-m", "cli", "serve", "--config", str(self.toml),
                                        "--port", str(self.port), *extra], stdout=subprocess.PIPE,
                                       stderr=subprocess.PIPE, text=True, env=self.env, cwd=ROOT)
        deadline = time.monotonic() + 60
        while True:
            assert self.daemon.poll() is None, self.daemon.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "station serve did not answer"
            try:
                if httpx.get(f"{self.base}/api/health", timeout=2).status_code == 200:
                    return self.daemon
            except httpx.HTTPError:
                pass
            time.sleep(0.2)

    def get(self, path: str) -> dict:
        r = httpx.get(self.base + path, headers=OPS, timeout=5)
        assert r.status_code == 200, r.text
        return r.json()

    def start_batch(self) -> int:
        r = httpx.post(f"{self.base}/api/batches", headers=OPS, json={"profile": "fast-thermal", "operator": "Ana"},
                       timeout=10)
        assert r.status_code == 201, r.text
        return int(r.json()["id"])

    def wait(self, cond, what: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not cond():
            assert time.monotonic() < deadline, f"timed out: {what}"
            time.sleep(0.1)

    def sigterm(self) -> float:
        """SIGTERM the daemon; seconds until it exited."""
        assert self.daemon is not None
        t0 = time.monotonic()
        self.daemon.send_signal(signal.SIGTERM)
        try:
            self.daemon.wait(60)
        except subprocess.TimeoutExpired:
            self.daemon.kill()
            raise
        return time.monotonic() - t0

    def close(self) -> None:
        if self.daemon is not None and self.daemon.poll() is None:
            self.daemon.kill()
            self.daemon.wait(10)
        self.sim.send_signal(signal.SIGTERM)
        try:
            self.sim.wait(20)
        except subprocess.TimeoutExpired:
            self.sim.kill()


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path)
    try:
        yield r
    finally:
        r.close()


def _page_storage_banner(base: str) -> str | None:
    """What the operator page's storage banner says (headless Chromium); None without a browser."""
    chromium = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if chromium is None:
        return None
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
        try:
            page = browser.new_page()
            page.goto(base + "/")
            page.wait_for_selector("#storage:not(.hidden)", timeout=15000)
            return page.inner_text("#storage")
        finally:
            browser.close()


def _stored(db_path: Path) -> tuple[dict, dict, dict]:
    """(samples per run, verdict records per run, verdict per run) as the database holds them."""
    db = Database(f"sqlite:///{db_path}")
    try:
        with db.session() as s:
            runs = s.execute(select(DutRun.id, DutRun.verdict)).all()
            records = dict(s.execute(select(VerdictHistoryRow.run_id, func.count()).group_by(VerdictHistoryRow.run_id)).all())
        samples = {rid: run_samples(db, rid) for rid, _ in runs}
        return samples, records, {rid: v for rid, v in runs}
    finally:
        db.dispose()


def _no_gap(time_s: np.ndarray) -> bool:
    dt = np.diff(time_s)
    return bool(dt.size) and float(dt.max()) < 1.5 * float(np.median(dt))


def _replace_with_another_database(path: Path) -> None:
    """What a careless restore does: another (empty, migrated) database renamed over the file."""
    other = path.with_name("other.db")
    db = Database(f"sqlite:///{other}")
    db.upgrade()
    db.dispose()  # checkpointed: one self-contained file
    os.replace(other, path)


@pytest.mark.timeout(400)
@pytest.mark.parametrize("fault", ["deleted", "replaced"])
def test_the_database_file_deleted_or_replaced_mid_batch_alarms_loses_nothing_and_the_restart_is_refused(rig, fault):
    rig.serve()
    bid = rig.start_batch()
    rig.wait(lambda: rig.get(f"/api/batches/{bid}")["step_index"] >= 1, "the batch mid-way", 120)
    t_delete = time.monotonic()
    if fault == "deleted":
        for p in rig.tmp.glob("station.db*"):
            if p.name in ("station.db", "station.db-wal", "station.db-shm"):
                p.unlink()
    else:
        _replace_with_another_database(rig.db_path)
    rig.wait(lambda: fault in str(httpx.get(f"{rig.base}/api/health", timeout=2).json()["db"]), "health says", 5)
    alarm_s = time.monotonic() - t_delete
    rig.wait(lambda: rig.get(f"/api/batches/{bid}")["state"] in ("finished", "failed", "aborted"), "batch end", 180)
    status = rig.get(f"/api/batches/{bid}")
    assert status["state"] == "finished", status["error"]
    counted = {s["run_id"]: s["samples"] for s in status["slots"]}
    assert all(s["decision"] for s in status["slots"])
    refused = httpx.post(f"{rig.base}/api/batches", headers=OPS, json={"profile": "fast-thermal", "operator": "Ana"},
                         timeout=10)
    assert refused.status_code == 503 and fault in refused.json()["detail"], refused.text
    health = httpx.get(f"{rig.base}/api/health", timeout=2).json()
    assert health["forwarding"]["events"] > 0, health
    banner = _page_storage_banner(rig.base)
    if banner is not None:  # the operator sees why a batch is refused and that nothing is lost
        assert fault in banner and "New batches cannot start" in banner, banner
        assert "records wait on this station to be forwarded" in banner and f"batch {bid}" in banner, banner
    assert rig.sigterm() < SIGTERM_BOUND_S
    rescued = sorted(rig.tmp.glob("station.db.rescued-*"))
    assert len(rescued) == 1, list(rig.tmp.iterdir())
    assert rig.db_path.exists() == (fault == "replaced")

    out = subprocess.run([sys.executable, "-m", "cli", "serve", "--config", str(rig.toml), "--no-web"],
                         capture_output=True, text=True, env=rig.env, cwd=ROOT, timeout=60)
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert out.returncode != 0 and len(lines) == 1, out.stderr
    assert "marker" in lines[0] and "--new-database" in lines[0] and "rescued" in lines[0], lines[0]
    assert rig.db_path.exists() == (fault == "replaced")  # the refusal made no new empty database

    shutil.copy(rescued[0], rig.db_path)  # the operator puts the rescued file back
    rig.serve()
    rig.wait(lambda: httpx.get(f"{rig.base}/api/health", timeout=2).json()["db"] == "ok", "journal forwarded", 60)
    assert rig.sigterm() < SIGTERM_BOUND_S
    samples, records, verdicts = _stored(rig.db_path)
    print(f"\nfile {fault} mid-batch: alarm after {alarm_s:.2f} s; the page: {banner!r}; refused restart: {lines[0]!r}; runs {counted}")
    assert alarm_s < 5.0
    for run_id, n in counted.items():
        assert len(samples[run_id]) == n, (run_id, len(samples[run_id]), n)
        assert _no_gap(samples[run_id].time_s), run_id
        assert records.get(run_id) == 1 and verdicts[run_id] is not None, (run_id, records, verdicts)


@pytest.mark.timeout(400)
def test_sigterm_while_another_process_holds_the_lock_ends_in_bound_and_loses_nothing(rig):
    rig.serve()
    bid = rig.start_batch()
    rig.wait(lambda: rig.get(f"/api/batches/{bid}")["step_index"] >= 1, "the batch mid-way", 120)
    locker = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(rig.db_path), "60"], stdout=subprocess.PIPE, text=True)
    try:
        assert locker.stdout.readline().split()[0] == "LOCKED"
        time.sleep(2.0)  # the writer's commit now waits on the lock; samples keep coming
        before = {s["run_id"]: s["samples"] for s in rig.get(f"/api/batches/{bid}")["slots"]}
        exit_s = rig.sigterm()
        assert rig.daemon.returncode == 0, rig.daemon.communicate()[1][-3000:]
    finally:
        locker.kill()
        locker.wait(10)
    journal = rig.tmp / "station.db.journal"
    assert journal.exists()
    rig.serve()  # the lock is gone: the journal is forwarded before anything else
    rig.wait(lambda: httpx.get(f"{rig.base}/api/health", timeout=2).json()["db"] == "ok", "journal forwarded", 60)
    assert rig.sigterm() < SIGTERM_BOUND_S
    samples, records, verdicts = _stored(rig.db_path)
    print(f"\nSIGTERM with the database locked: exit after {exit_s:.2f} s; samples at SIGTERM {before}, stored "
          f"{ {k: len(v) for k, v in samples.items()} }")
    assert exit_s < SIGTERM_BOUND_S
    for run_id, n in before.items():
        assert len(samples[run_id]) >= n, (run_id, len(samples[run_id]), n)  # and those after, up to the stop
        assert _no_gap(samples[run_id].time_s), run_id
        assert records.get(run_id) == 1 and verdicts[run_id] == "error", (run_id, records, verdicts)
