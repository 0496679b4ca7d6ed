"""A station batch's stored run, diagnosed the two ways an engineer can, ranks like its log without
the plate moves (issue 38).

The daemon stores every sample taken while the plate moves at position -1 (the contract: "moving or
unknown"; tests/test_sequencer.py test_position_is_unknown_while_the_plate_moves). Those samples
belong to no orientation: a diagnosis must never fit them. Before, one -1 row made the diagnosis
ignore the position column and cluster the readings by acceleration instead ("orientation o0"),
with the move's samples fitted as data: another held-out error, another ranking.

A fast-thermal batch (P ambient, P hot, turn, N hot, N ambient: lamp heating of ~40 C) runs on a
simulated board with a hidden bias_t2 through the real daemon and fixture into SQLite. Its run is
diagnosed (a) through the REST API the page's Diagnose uses (GET /api/runs/{id}/diagnosis, the run
read from the database) and (b) through the CLI (`station db export` of the run, then `station
diagnose LOG.csv --json`); both must give the ranking of the same log with its -1 rows removed:
the effects in the same order, the same admitted list, the same held-out errors (to 1e-6 mg).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from contracts.logfile import DutLog, read_log, write_log

ROOT = Path(__file__).resolve().parents[1]
SPEED = 1000.0  # a fast-thermal batch in ~5 s; the plate's 4 s moves still give ~16 samples at -1 each
SEED = 5
TOKEN = "diag-station-run-token-0123"
TOL_MG = 1e-6


def _station(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True, timeout=300,
                          cwd=ROOT)


@pytest.fixture(scope="module")
def stored_run(tmp_path_factory):
    """(tmp dir, database URL, run id, the DUT's truth) of a finished fast-thermal batch."""
    from db import repository as repo
    from drivers.sim.station_sim import SimStation
    from test_daemon_e2e import daemon

    tmp = tmp_path_factory.mktemp("station_run")

    async def batch():
        async with SimStation(n_serial=1, n_can=0, seed=SEED, speed=SPEED, effects=("bias_t2",)) as sim:
            async with daemon(sim, tmp, SPEED) as st:  # the simulated fixture turns the plate
                bid = st.start_batch("fast-thermal", None, "pytest")
                status = await st.wait_batch(bid, timeout_s=250)
                assert status["state"] == "finished", status["error"]
                assert [s["state"] for s in status["slots"]] == ["done"], status["slots"]
                await st.flush_db()
                return repo.batch_detail(st.db, bid)["runs"][0]["id"], sim.truths[0]

    run_id, truth = asyncio.run(batch())
    return tmp, f"sqlite:///{tmp / 'station.db'}", run_id, truth


def _ranking(doc: dict) -> dict:
    """What must agree: the effects in order, the admitted list, every held-out error."""
    return {"order": [r["effect"] for r in doc["ranking"]],
            "admitted": list(doc["admitted"]),
            "ranking_admitted": [r["effect"] for r in doc["ranking"] if r["admitted"]],
            "heldout": {r["effect"]: r["heldout_rms_mg"] for r in doc["ranking"]},
            "baseline_heldout": doc["baseline"]["heldout_rms_mg"],
            "staircase_heldout": [s["heldout_rms_mg"] for s in doc["admitted_staircase"]]}


def _assert_same_ranking(got: dict, want: dict, what: str) -> None:
    a, b = _ranking(got), _ranking(want)
    assert a["order"] == b["order"], (what, a["order"], b["order"])
    assert a["admitted"] == b["admitted"] and a["ranking_admitted"] == b["ranking_admitted"], (what, a, b)
    for eff, v in b["heldout"].items():
        assert a["heldout"][eff] == pytest.approx(v, abs=TOL_MG), (what, eff, a["heldout"][eff], v)
    assert a["baseline_heldout"] == pytest.approx(b["baseline_heldout"], abs=TOL_MG), (what, a, b)
    assert a["staircase_heldout"] == pytest.approx(b["staircase_heldout"], abs=TOL_MG), (what, a, b)


def _without_moves(log: DutLog) -> DutLog:
    assert log.position is not None
    keep = log.position >= 0
    return DutLog(time_s=log.time_s[keep], acc_g=log.acc_g[keep], temp_c=log.temp_c[keep], meta=dict(log.meta),
                  lamp=None if log.lamp is None else log.lamp[keep], position=log.position[keep],
                  ref_dir=None if log.ref_dir is None else log.ref_dir[keep])


def test_the_stored_run_holds_its_plate_moves_at_position_minus_1(stored_run):
    from db import Database
    from db.export import run_log

    _, url, run_id, _ = stored_run
    db = Database(url)
    try:
        log = run_log(db, run_id)
    finally:
        db.dispose()
    pos = log.position
    assert pos is not None and set(np.unique(pos).tolist()) == {-1, 0, 1}, np.unique(pos)
    # the turn from P to N: every sample between the last at P and the first at N is a move (-1)
    last_p, first_n = int(np.flatnonzero(pos == 0)[-1]), int(np.flatnonzero(pos == 1)[0])
    assert last_p < first_n and first_n - last_p - 1 >= 3 and np.all(pos[last_p + 1:first_n] == -1)
    assert np.ptp(log.temp_c) >= 20.0  # the lamp heated the plate: something to diagnose


def test_rest_and_cli_rank_the_run_as_its_log_without_the_moves(stored_run):
    from db import Database
    from web.app import create_app
    from web.auth import TokenStore
    from web.db_repo import DbRepository

    tmp, url, run_id, truth = stored_run
    # (b) the CLI: the run exported from the database, then diagnosed
    csv = tmp / "run.csv"
    exp = _station("db", "--url", url, "export", str(run_id), "--out", str(csv))
    assert exp.returncode == 0, exp.stderr
    out = _station("diagnose", str(csv), "--json")
    assert out.returncode == 0, out.stderr
    cli = json.loads(out.stdout)
    # the reference: the same log with its -1 rows removed
    log = read_log(csv)
    assert log.position is not None and (log.position == -1).sum() >= 3
    clean_csv = tmp / "run_without_moves.csv"
    write_log(clean_csv, _without_moves(log))
    out = _station("diagnose", str(clean_csv), "--json")
    assert out.returncode == 0, out.stderr
    clean = json.loads(out.stdout)
    assert "bias_t2" in clean["admitted"], clean["admitted"]  # the hidden effect: the reference ranks right

    # (a) the REST API the page's Diagnose calls, the run read from the database
    db = Database(url)
    try:
        app = create_app(SimpleNamespace(config=None, bus=None, db=None), repo=DbRepository(db),
                         tokens=TokenStore([(TOKEN, "operator", "op")]), outbox=False)
        with TestClient(app) as c:
            r = c.get(f"/api/runs/{run_id}/diagnosis", headers={"Authorization": f"Bearer {TOKEN}"})
            assert r.status_code == 200, r.text
            rest = r.json()
    finally:
        db.dispose()

    _assert_same_ranking(rest, clean, "REST")
    _assert_same_ranking(cli, clean, "CLI")
    # the moves are no orientation: the run's two positions, named as the CLI names them
    assert rest["orientations"] == {truth.serial: [{"label": "0", "name": "position 0 (P)"},
                                                   {"label": "1", "name": "position 1 (N)"}]}
    assert rest["data_features"]["orientations"] == clean["data_features"]["orientations"] == 2
    for doc in (rest, cli):
        for nv in doc["noise"].values():
            assert "orientation o" not in nv["statement"], nv["statement"]
