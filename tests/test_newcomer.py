"""Issue 9, a newcomer's first hour: what the station says about a batch must be right and plain.

One LiveStation (2 serial boards, fixture, SQLite) runs a two-step validation-like profile
("look": a short dwell, "hold": until aborted, analysis none) over HTTP:

- the status says what the current step waits for, the elapsed time, that this profile yields no
  calibration result, and per DUT the steps actually done (the page's progress dots);
- after an abort nothing counts as running, and the batch says who ended it and when
  ("aborted by test-operator at ...": ended_by / ended_at);
- each DUT's plot is its own run's (plot_url by run_id), also once the serial has a newer run;
- GET /api/profiles describes every profile (description, analysis kind, step count);
- /favicon.ico is answered.
"""

from __future__ import annotations

import re
import time
from datetime import datetime, timezone

import httpx
import numpy as np
import pytest

from web_support import LiveStation, auth, wait_for

TERMINAL = {"finished", "aborted", "failed", "interrupted"}
LOOK_HOLD = {"look-hold": {
    "description": "test: a short look at P, then hold until aborted", "analysis": "none",
    "steps": [{"name": "look", "position": "P", "lamp": False, "require": "none", "dwell_s": 3.0, "timeout_s": 600},
              {"name": "hold", "position": "P", "lamp": False, "require": "none", "dwell_s": 1e6, "timeout_s": 2e6}]}}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveStation(tmp_path_factory.mktemp("newcomer"), n_serial=2, n_can=0, speed=400.0, fixture=True,
                     profiles=LOOK_HOLD) as ls:
        yield ls


@pytest.fixture(scope="module")
def client(live):
    with httpx.Client(base_url=live.url, timeout=30) as c:
        yield c


def status(client, bid):
    return client.get(f"/api/batches/{bid}", headers=auth("operator")).json()


def start(client):
    r = client.post("/api/batches", json={"profile": "look-hold", "operator": "Ana"}, headers=auth("operator"))
    assert r.status_code == 201, r.text
    return r.json()["id"]


def abort_and_wait(client, bid):
    r = client.post(f"/api/batches/{bid}/abort", headers=auth("operator"))
    assert r.status_code == 200, r.text
    return wait_for(lambda: (s := status(client, bid))["state"] in TERMINAL
                    and all(x["state"] not in ("connecting", "identified", "running") for x in s["slots"]) and s,
                    30, what="abort")


def test_abort_counts_who_and_when_progress_waiting_and_own_plots(live, client):
    bid = start(client)
    # in the second step: one step done per DUT, what it waits for, no calibration result to expect
    st = wait_for(lambda: (s := status(client, bid))["step"]["index"] == 1 and s.get("seq_state") == "logging" and s,
                  60, what="step 2 logging")
    assert st["analysis"] == "none" and "no calibration result" in st["note"]
    assert st["waiting_for"] == "dwell"
    assert st["counts"] == {"running": 2, "done": 0, "faulted": 0, "interrupted": 0}
    for s in st["slots"]:
        assert s["steps_done"] == 1, s
        assert s["waiting_for"] == "dwell"
    assert st["elapsed_s"] > 0 and st["ended_by"] is None and st["ended_at"] is None
    assert st["time_left"]["step_wall_s"] is not None

    before = datetime.now(timezone.utc).replace(microsecond=0)
    st = abort_and_wait(client, bid)
    after = datetime.now(timezone.utc)
    assert st["state"] == "aborted"
    # nothing runs after an abort; the error box says who and when
    assert st["counts"] == {"running": 0, "done": 0, "faulted": 0, "interrupted": 2}
    assert st["ended_by"] == "test-operator"
    ended = datetime.fromisoformat(st["ended_at"].replace("Z", "+00:00"))
    assert before <= ended <= after
    assert re.fullmatch(r"aborted by test-operator at \d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", st["error"]), st["error"]
    assert st["waiting_for"] is None and all(s["waiting_for"] is None for s in st["slots"])
    assert all(s["steps_done"] == 1 for s in st["slots"])
    elapsed = st["elapsed_s"]
    time.sleep(0.3)
    assert status(client, bid)["elapsed_s"] == elapsed  # stops at the end
    # the same after a restart (the batch then comes from the database)
    live.flush_db()
    stored = live.app.state.repo.batch(bid)
    assert stored["counts"] == st["counts"] and stored["error"] == st["error"] and stored["ended_at"]

    # each interrupted DUT's plot is its own run, also once its serial has a newer run
    first = {s["slot"]: (s["serial"], s["run_id"], s["plot_url"]) for s in st["slots"]}
    bid2 = start(client)
    try:
        wait_for(lambda: all(s.get("run_id") and s["samples"] > 20 for s in status(client, bid2)["slots"]), 30,
                 what="second batch runs with samples")
    finally:
        abort_and_wait(client, bid2)
    live.flush_db()
    st = status(client, bid)
    for s in st["slots"]:
        serial, run_id, plot_url = first[s["slot"]]
        assert s["run_id"] == run_id and plot_url == s["plot_url"] == f"/api/runs/{run_id}/plot.png"
        run = client.get(f"/api/runs/{run_id}", headers=auth("operator")).json()
        assert (run["batch_id"], run["slot"], run["serial"], run["state"]) == (bid, s["slot"], serial, "interrupted")
        latest = client.get(f"/api/duts/{serial}/runs", headers=auth("operator")).json()[0]
        assert latest["id"] != run_id and latest["batch_id"] == bid2  # the serial's latest is another run
        png = client.get(plot_url, headers=auth("operator"))
        assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
        # the newer run starts with its own samples: none left over from the board's previous run
        # (they made a gap of the time between the batches at the start of its plot)
        t = live.app.state.repo.run_log(latest["id"]).time_s
        assert len(t) > 20 and float(np.max(np.diff(t))) < 2.0, (t[:3], float(np.max(np.diff(t))))


def test_profiles_are_described(client):
    profiles = {p["name"]: p for p in client.get("/api/profiles", headers=auth("mes")).json()}
    for name in ("fast-thermal", "fast-thermal-verified", "six-position", "sfem-24", "validation"):
        p = profiles[name]
        assert p["description"] and len(p["description"]) > 20, p
        assert p["analysis"] in ("thermal", "sfem", "none") and p["n_steps"] >= 1 and p["builtin"] is True
    assert profiles["fast-thermal"]["analysis"] == "thermal" and profiles["fast-thermal"]["n_steps"] == 4
    assert profiles["validation"]["analysis"] == "none"
    assert profiles["look-hold"] == {**profiles["look-hold"], "description": LOOK_HOLD["look-hold"]["description"],
                                     "analysis": "none", "n_steps": 2, "builtin": False}


def test_favicon_is_served(client):
    r = client.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/")
    assert b"<svg" in r.content and len(r.content) < 2000
    assert 'rel="icon" href="/favicon.ico"' in client.get("/").text


def test_run_plots_use_time_since_the_runs_first_sample():
    """Board clocks count from power-up (here 73000 s): the plot's axis starts at the run's first sample."""
    import numpy as np

    from contracts.logfile import DutLog
    from web.plots import render_run_png, run_figure

    t = 73000.0 + np.arange(300) / 3.125
    log = DutLog(t, np.tile([0.0, 0.0, 1.0], (300, 1)), np.full(300, 25.0))
    segs = [{"t_start_s": 73010.0, "t_end_s": 73020.0}]
    fig = run_figure(log, segs, None, "run 1")
    axs = fig.get_axes()
    xs = axs[0].lines[0].get_xdata()
    assert xs[0] == 0.0 and abs(xs[-1] - (t[-1] - t[0])) < 1e-9
    span = axs[0].patches[0]  # the logged segment, shifted alike (a Rectangle, or a Polygon before mpl 3.9)
    xs = [span.get_x(), span.get_x() + span.get_width()] if hasattr(span, "get_width") else [p[0] for p in span.get_xy()]
    assert {round(float(x), 6) for x in xs} == {10.0, 20.0}
    assert "first sample" in axs[3].get_xlabel()
    assert render_run_png(log, segs, None)[:4] == b"\x89PNG"


def test_docs_are_carried_in_the_repository():
    """README points into docs/ (not to a file outside the repository); the design keeps every
    contract section, the position during moves, and the status fields a newcomer reads."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    assert "../shared" not in readme
    for doc in ("docs/design.md", "docs/cli.md", "docs/operator-page.md"):
        assert f"]({doc})" in readme, doc
        assert (root / doc).stat().st_size > 2000, doc
    design = (root / "docs/design.md").read_text()
    for head in ("### 3.1 Serial board", "### 3.2 CAN board", "### 3.3 Modbus devices", "### 5.1 Log file",
                 "### 5.2 Command line", "### 5.3 REST", "## 7. Model diagnostics"):
        assert head in design, head
    assert re.search(r"moves.*position is unknown: null in the status and `-1`", design, re.S)
    for field in ("waiting_for", "ended_by", "ended_at", "counts", "steps_done", "plot_url", "elapsed_s"):
        assert f"`{field}`" in design, field
    cli = (root / "docs/cli.md").read_text()
    assert "unknown profile 'nope'" in cli and "station serve" in cli
