"""The line's day over real HTTP (issue 24): a batch started with a work order, part, lot and the
label serials scanned per slot; a mismatching label stops its slot and only it; the step list,
progress and countdown while it runs (program and verify included); every record carries the
trace; "Retest failed" starts only the error, fail and marginal slots with their labels scanned
again (a label its board contradicted is never reused); "cannot do it" at a prompt ends the DUTs as
error with the operator's words, and their slots are ready for the next batch; batch.start is audited
for every start, naming the person.

Truth: the simulated boards' own serials (GET /api/slots after connect), rows in the SQLite file,
the MES feed and the audit trail.
"""

from __future__ import annotations

import math
import sqlite3
import time

import httpx
import pytest

from station.daemon.progress import COUNTDOWN_MAX_RATE, Countdown
from web.mes_outbox import payload_of
from web_support import LiveStation, auth

TRACE = {"work_order": "WO-24017", "part_number": "ACC-3X-100", "part_revision": "C", "lot": "L2611-07"}


def _wait_status(api, bid: int, pred, timeout_s: float, samples: list | None = None, every_s: float = 0.25) -> dict:
    end = time.monotonic() + timeout_s
    while True:
        st = api.get(f"/api/batches/{bid}").json()
        if samples is not None:
            samples.append((time.monotonic(), st))
        if pred(st):
            return st
        assert time.monotonic() < end, f"batch {bid} did not get there in {timeout_s} s: {st.get('state')}"
        time.sleep(every_s)


def _serials(api) -> dict[str, str]:
    slots = api.get("/api/slots").json()
    return {s["slot"]: s["serial"] for s in slots}


def test_work_order_labels_steps_countdown_and_retest(tmp_path):
    with LiveStation(tmp_path, n_serial=3, n_can=0, speed=400.0, fixture=True) as live, \
            httpx.Client(base_url=live.url, timeout=30, headers={**auth("operator"), "X-Operator": "Ana"}) as api:
        serials = _serials(api)
        assert all(serials.values()), serials
        slots = sorted(serials)
        wrong = slots[1]
        labels = {slots[0]: f" {serials[slots[0]].lower()} ",  # scanners add whitespace; case-insensitive
                  wrong: "SN-NOT-THIS-BOARD"}
        r = api.post("/api/batches", json={"profile": "fast-thermal-verified", "slots": slots, "operator": "Ana",
                                           **TRACE, "labels": labels})
        assert r.status_code == 201, r.text
        bid = r.json()["id"]

        samples: list = []
        st = _wait_status(api, bid, lambda s: s["state"] not in ("running", "paused", "created"), 240, samples)
        assert st["state"] == "finished", st.get("error")
        assert {k: st[k] for k in TRACE} == TRACE

        by_slot = {s["slot"]: s for s in st["slots"]}
        # the mismatching label stopped its slot, with the reason; the others ran on
        assert by_slot[wrong]["state"] == "faulted" and by_slot[wrong]["verdict"] == "error"
        assert "SN-NOT-THIS-BOARD" in by_slot[wrong]["error"] and serials[wrong] in by_slot[wrong]["error"]
        for s in slots:
            if s != wrong:
                assert by_slot[s]["state"] == "done" and by_slot[s]["verdict"] in ("pass", "marginal", "fail")
        assert by_slot[slots[0]]["label_serial"] == serials[slots[0]].lower()

        # the step list: every profile step and the analysis, program and verify named; all done at the end
        steps = st["steps"]
        assert [r["kind"] for r in steps].count("program") == 1 and "verify" in [r["kind"] for r in steps]
        assert steps[-1]["kind"] == "analysis" and all(r["state"] == "done" for r in steps), steps
        assert all(r["duration_s"] is not None and r["duration_s"] >= 0 for r in steps)
        assert st["progress"] == 1.0 and st["time_left"]["batch_wall_s"] == 0.0

        running = [(t, s) for t, s in samples if s["state"] in ("running", "paused")]
        assert len(running) >= 20, len(running)
        # the countdown never goes up, and never shows 0:00 while work remains (program, verify, analysis)
        lefts = [s["time_left"]["batch_wall_s"] for _, s in running]
        assert all(b <= a + 1e-6 for a, b in zip(lefts, lefts[1:])), lefts
        assert all(v > 0 for v in lefts), lefts
        seen_kinds = {next((r["kind"] for r in s["steps"] if r["state"] == "running"), None) for _, s in running}
        assert {"program", "verify"} <= seen_kinds, seen_kinds
        # steady: between two estimates it falls by at most COUNTDOWN_MAX_RATE x the wall time
        # between them (the server's own clock: an answer may come from the 0.1 s status cache)
        for a, b in zip(running, running[1:]):
            ta, tb = a[1]["time_left"], b[1]["time_left"]
            drop = ta["batch_wall_s"] - tb["batch_wall_s"]
            assert drop <= COUNTDOWN_MAX_RATE * (tb["estimated_at"] - ta["estimated_at"]) + 0.01, (ta, tb)
        progress = [s["progress"] for _, s in running]
        assert all(0.0 <= p <= 1.0 for p in progress) and all(b >= a for a, b in zip(progress, progress[1:]))
        # one step runs at a time, and the running one only moves forward
        idx = [next((r["index"] for r in s["steps"] if r["state"] == "running"), None) for _, s in running]
        idx = [i for i in idx if i is not None]
        assert idx == sorted(idx) and len(set(idx)) >= 4

        # rows in the database: the batch's trace, each run's label serial
        live.flush_db()
        con = sqlite3.connect(live.db_path)
        row = con.execute("SELECT work_order, part_number, part_revision, lot, operator FROM batch WHERE id=?",
                          (bid,)).fetchone()
        assert row == (*TRACE.values(), "Ana")
        runs = dict(con.execute("SELECT slot, label_serial FROM dut_run WHERE batch_id=?", (bid,)).fetchall())
        assert runs[wrong] == "SN-NOT-THIS-BOARD" and runs[slots[2]] is None
        # the MES record carries the trace and the label; the faulted slot is an error record
        mes = httpx.get(f"{live.url}/api/results", params={"since": 0}, headers=auth("mes")).json()["results"]
        mine = {m["slot"]: m for m in mes if m["batch_id"] == bid}
        assert set(mine) == set(slots)
        assert all({k: m[k] for k in TRACE} == TRACE and m["operator"] == "Ana" for m in mine.values())
        assert mine[wrong]["verdict"] == "error" and mine[wrong]["label_serial"] == "SN-NOT-THIS-BOARD"
        # the webhook body carries the same (web/mes_outbox.py payload_of of the feed's record)
        hook = payload_of(mine[wrong], "line-1")
        assert {k: hook[k] for k in TRACE} == TRACE and hook["label_serial"] == "SN-NOT-THIS-BOARD"
        assert hook["operator"] == "Ana" and hook["verdict"] == "error"
        # the audit names the person, and through what it was started
        audit = httpx.get(f"{live.url}/api/audit", headers=auth("admin")).json()
        start = [a for a in audit if a["action"] == "batch.start" and a["target"] == f"batch {bid}"]
        assert len(start) == 1 and start[0]["actor"] == "Ana"
        assert start[0]["detail"]["via"].startswith("REST: Ana (token") and start[0]["detail"]["work_order"] == TRACE["work_order"]

        # Retest failed: only the error, fail and marginal slots, same profile and trace, the new
        # operator; the wrong label is never reused: it is scanned again (tests/test_retest_labels.py)
        retest_slots = sorted(s for s in slots if by_slot[s]["verdict"] in ("fail", "error", "marginal"))
        assert api.post(f"/api/batches/{bid}/retest", json={"operator": "  "}).status_code == 422
        r = api.post(f"/api/batches/{bid}/retest", json={"operator": "Bo"})
        assert r.status_code == 409 and "SN-NOT-THIS-BOARD" in r.json()["detail"], r.text
        r = api.post(f"/api/batches/{bid}/retest", json={"operator": "Bo", "labels": {wrong: serials[wrong]}})
        assert r.status_code == 201, r.text
        bid2 = r.json()["id"]
        st2 = _wait_status(api, bid2, lambda s: s["state"] not in ("running", "paused", "created"), 120)
        assert sorted(s["slot"] for s in st2["slots"]) == retest_slots
        assert {k: st2[k] for k in TRACE} == TRACE and st2["operator"] == "Bo" and st2["profile"] == "fast-thermal-verified"
        assert st2["labels"] == {wrong: serials[wrong]}  # the label scanned again: the board's own


def test_retest_refuses_a_batch_without_error_fail_or_marginal_slots_and_a_running_one(tmp_path):
    from types import SimpleNamespace as NS

    from contracts.trace import Trace
    from db.database import Database
    from station.daemon.batches import BatchDesk
    from test_retest_labels import _desk

    retest_batch = BatchDesk.retest_batch

    db = Database(f"sqlite:///{tmp_path / 'empty.db'}")  # holds no batch: 8 is unknown there too
    db.upgrade()

    def station(state: str, verdicts: dict):
        duts = [NS(slot=k, verdict={"verdict": v} if v else None, label_serial=None, identity=None)
                for k, v in verdicts.items()]
        seq = NS(state=state, duts=duts, trace=Trace(), profile=NS(name="fast-thermal"))
        return _desk({7: seq}, list(verdicts), db)

    with pytest.raises(ValueError, match="no slot that ended error, fail or marginal"):
        retest_batch(station("finished", {"a": "pass", "b": None}), 7, "Bo")
    with pytest.raises(ValueError, match="still logging"):
        retest_batch(station("logging", {"a": "fail"}), 7, "Bo")
    with pytest.raises(KeyError):
        retest_batch(station("finished", {"a": "fail"}), 8, "Bo")
    db.dispose()


def test_cannot_do_it_ends_the_duts_as_error_with_the_operators_words(tmp_path):
    with LiveStation(tmp_path, n_serial=2, n_can=1, speed=400.0, fixture=False) as live, \
            httpx.Client(base_url=live.url, timeout=30, headers={**auth("operator"), "X-Operator": "Ana"}) as api:
        r = api.post("/api/batches", json={"profile": "fast-thermal", "operator": "Ana", **TRACE})
        assert r.status_code == 201, r.text
        bid = r.json()["id"]
        st = _wait_status(api, bid, lambda s: s["prompt"] is not None, 60)
        prompt = st["prompt"]
        # the picture's truth: the gravity direction of the asked position in the board's frame
        assert prompt["kind"] == "turn_plate" and prompt["position_name"] == "P"
        assert all(math.isclose(v, 1 / math.sqrt(3), abs_tol=1e-5) for v in prompt["direction"])
        pid = prompt["prompt_id"]
        r = api.post(f"/api/batches/{bid}/prompt", json={"prompt_id": pid, "answer": "cannot"})
        assert r.status_code == 422 and "why" in r.text  # the words are required
        r = api.post(f"/api/batches/{bid}/prompt", json={"prompt_id": pid, "answer": "later"})
        assert r.status_code == 422
        r = api.post(f"/api/batches/{bid}/prompt",
                     json={"prompt_id": pid, "answer": "cannot", "note": "plate hinge jammed, called maintenance"})
        assert r.status_code == 200, r.text
        st = _wait_status(api, bid, lambda s: s["state"] not in ("running", "paused", "created"), 30)
        assert st["state"] == "failed" and "plate hinge jammed" in st["error"]
        assert st["lamp_on"] is False
        assert st["slots"] and all(s["state"] == "faulted" and s["verdict"] == "error" for s in st["slots"])
        assert all("plate hinge jammed, called maintenance" in s["reason"] for s in st["slots"])
        assert all("Ana" in s["error"] and "turn the plate to P" in s["error"] for s in st["slots"])
        rows = [r for r in st["steps"] if r["state"] in ("failed", "skipped")]
        assert rows and st["steps"][0]["state"] == "failed" and st["progress"] is None
        audit = httpx.get(f"{live.url}/api/audit", headers=auth("admin")).json()
        answer = [a for a in audit if a["action"] == "prompt.answer"]
        assert answer[0]["detail"]["note"] == "plate hinge jammed, called maintenance"
        assert answer[0]["actor"].startswith("Ana (token")
        # every DUT faulted, every board still answers: every slot is ready for the next batch
        slots = api.get("/api/slots").json()
        assert all(s["state"] == "identified" and not s["fault_reason"] for s in slots), slots


def test_every_start_is_audited_naming_the_person_demo_and_replay_included(tmp_path):
    """station demo and station replay start through Station.start_batch with by='station demo'
    / 'station replay' (cli/commands/demo.py, station/replay/runner.py): the same code path."""
    with LiveStation(tmp_path, n_serial=1, n_can=0, speed=400.0, fixture=True) as live:
        with pytest.raises(ValueError, match="operator's name is required"):
            live.call(live.station.start_batch, "validation", None, "  ", by="station demo")
        bid = live.call(live.station.start_batch, "validation", None, "demo", by="station demo")
        live.call(live.station.wait_batch, bid, 60)
        audit = httpx.get(f"{live.url}/api/audit", headers=auth("admin")).json()
        start = [a for a in audit if a["action"] == "batch.start"]
        assert len(start) == 1 and start[0]["actor"] == "demo" and start[0]["detail"]["via"] == "station demo"


def test_countdown_never_rises_runs_steady_and_reaches_zero_only_with_the_work():
    c = Countdown()
    assert c.update(100.0, now=0.0) == 100.0
    # the estimate agrees: one second per second
    assert math.isclose(c.update(90.0, now=10.0), 90.0)
    # the estimate jumps up (a slow segment): the countdown does not rise, it slows down
    v = c.update(180.0, now=11.0)
    assert 89.0 < v < 90.0
    # the estimate drops (a step ended early): faster, at most COUNTDOWN_MAX_RATE
    v2 = c.update(10.0, now=12.0)
    assert v - COUNTDOWN_MAX_RATE - 1e-9 <= v2 < v - 1.0
    # work remains: never 0 however long it takes
    t = 12.0
    for _ in range(2000):
        t += 1.0
        last = c.update(5.0, now=t)
    assert last > 0.0
    assert c.update(0.0, now=t + 100.0) == 0.0
