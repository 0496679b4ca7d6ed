"""Every way back from a mistake at the plate (issue 34), over real HTTP against the real daemon
(simulated boards on ptys, Modbus relay and fixture on 127.0.0.1) and its SQLite file:

1. A label mismatch (s3 scanned as SIM9999) stops that slot before any data; its run is stored and
   judged error for the MES, but it is NO attempt of the board's serial (attempt 0): attempts,
   first-pass and final yield stay true. The slot is ready again once the batch ended (its board
   answered). "Retest failed" without labels refuses to reuse the wrong label; with the label scanned
   again it runs only the error/fail/marginal slots, and the serial's first real run is attempt 1.
2. Slots after a batch: a slot whose DUT faulted while its board still answers is `identified`
   (ready, ticked on the page) after the batch; a slot whose board is gone (link lost) keeps that
   reason and can still be chosen for the next batch, whose connect tries it again.
3. retest_batch's rules on a stand-in station: which verdicts, which labels, which slots.

Truth: the simulated boards' own serials (GET /api/slots before the batch), rows in the SQLite file.
"""

from __future__ import annotations

import os

import sqlite3
import time
from types import SimpleNamespace as NS

import httpx
import pytest

from contracts.trace import Trace
from web_support import LiveStation, auth

TRACE = {"work_order": "WO-34", "part_number": "ACC-3X-100", "part_revision": "C", "lot": "L34"}
ENDED = ("finished", "failed", "aborted", "interrupted")


def _wait(api, bid: int, pred, timeout_s: float, what: str) -> dict:
    end = time.monotonic() + timeout_s
    while True:
        st = api.get(f"/api/batches/{bid}").json()
        if pred(st):
            return st
        assert time.monotonic() < end, f"batch {bid}: {what} not within {timeout_s} s (state {st.get('state')})"
        time.sleep(0.2)


def _judged(st: dict) -> bool:
    return st["state"] in ENDED and all(s.get("verdict") for s in st["slots"])


def _slots(api) -> dict[str, dict]:
    return {s["slot"]: s for s in api.get("/api/slots").json()}


def test_label_mismatch_is_no_attempt_and_is_mended_by_a_retest_with_the_label_scanned_again(tmp_path):
    with LiveStation(tmp_path, n_serial=3, n_can=0, speed=400.0, fixture=True) as live, \
            httpx.Client(base_url=live.url, timeout=30, headers={**auth("operator"), "X-Operator": "Ana"}) as api:
        serials = {k: s["serial"] for k, s in _slots(api).items()}
        assert all(serials.values()), serials
        labels = {"s1": serials["s1"], "s3": "SIM9999"}  # s3's label is another part's; s2 unlabelled
        r = api.post("/api/batches", json={"profile": "fast-thermal", "operator": "Ana", **TRACE, "labels": labels})
        assert r.status_code == 201, r.text
        bid = r.json()["id"]
        st = _wait(api, bid, _judged, 240, "the end and every verdict")
        assert st["state"] == "finished", st.get("error")
        by = {s["slot"]: s for s in st["slots"]}
        # the mismatch stopped s3 alone, with the reason; no attempt of its board's serial
        assert by["s3"]["state"] == "faulted" and by["s3"]["verdict"] == "error"
        assert "label serial 'SIM9999' does not match the board's own serial" in by["s3"]["error"]
        assert by["s3"]["attempt"] == 0 and by["s3"]["samples"] == 0
        for k in ("s1", "s2"):
            assert by[k]["state"] == "done" and by[k]["verdict"] in ("pass", "marginal", "fail") and by[k]["attempt"] == 1

        # the slot is ready for the next batch: its board answered at the end (the run keeps its fault)
        after = _slots(api)
        assert after["s3"]["state"] == "identified" and after["s3"]["fault_reason"] == "", after["s3"]
        assert after["s3"]["serial"] == serials["s3"]
        assert all(after[k]["state"] == "identified" for k in ("s1", "s2")), after

        # the MES and the history see which board was there and why it stopped ...
        live.flush_db()
        mes = httpx.get(f"{live.url}/api/results", params={"since": 0}, headers=auth("mes")).json()["results"]
        rec = next(m for m in mes if m["batch_id"] == bid and m["slot"] == "s3")
        assert (rec["serial"], rec["verdict"], rec["attempt"], rec["label_serial"]) == (serials["s3"], "error", 0, "SIM9999")
        runs = api.get(f"/api/duts/{serials['s3']}/runs").json()
        assert [(r["attempt"], r["verdict"], r["state"]) for r in runs] == [(0, "error", "faulted")]
        # ... but it is no attempt of that serial: no attempts, no result, no yield point
        dut = api.get(f"/api/duts/{serials['s3']}").json()
        assert (dut["attempts"], dut["n_runs"], dut["verdict"], dut["attempt"]) == (0, 1, None, None), dut
        y = httpx.get(f"{live.url}/api/yield", params={"batch_id": bid}, headers=auth("mes")).json()
        first = sum(by[k]["verdict"] == "pass" for k in ("s1", "s2"))
        assert (y["duts"], y["attempts"], y["first_pass"], y["final_pass"]) == (2, 2, first, first), y
        spc = api.get("/api/records/spc").json()
        per_batch = {row["key"]: row for row in spc["yield"]["batch"]}
        assert per_batch[str(bid)]["judged"] == 2, per_batch  # the records' yield table: tested runs only

        # Retest failed: the wrong label is never reused; only slots that ended error, fail or marginal
        again = sorted(k for k, s in by.items() if s["verdict"] in ("error", "fail", "marginal"))
        assert "s3" in again
        r = api.post(f"/api/batches/{bid}/retest", json={"operator": "Bo"})
        assert r.status_code == 409, r.text
        assert "SIM9999" in r.json()["detail"] and "scan the part's label again" in r.json()["detail"]
        assert api.post(f"/api/batches/{bid}/retest", json={"labels": {"s3": serials["s3"]}}).status_code == 422
        passed = sorted(set(by) - set(again))
        if passed:  # a pass is final: not retested
            r = api.post(f"/api/batches/{bid}/retest", json={"operator": "Bo", "slots": passed[:1], "labels": {}})
            assert r.status_code == 409 and "did not end error, fail or marginal" in r.json()["detail"], r.text
        r = api.post(f"/api/batches/{bid}/retest", json={"operator": "Bo", "labels": {"s3": f" {serials['s3']} "}})
        assert r.status_code == 201, r.text
        bid2 = r.json()["id"]
        st2 = _wait(api, bid2, _judged, 240, "the retest's end and verdicts")
        assert st2["state"] == "finished", st2.get("error")
        assert sorted(s["slot"] for s in st2["slots"]) == again
        assert st2["labels"] == {"s3": serials["s3"]} and st2["operator"] == "Bo"
        assert {k: st2[k] for k in TRACE} == TRACE and st2["profile"] == "fast-thermal"
        s3 = next(s for s in st2["slots"] if s["slot"] == "s3")
        assert s3["state"] == "done" and s3["verdict"] in ("pass", "marginal", "fail"), s3  # judged on its merit
        assert s3["attempt"] == 1 and s3["samples"] > 0  # the first run that tested the part

        live.flush_db()
        runs = api.get(f"/api/duts/{serials['s3']}/runs").json()
        assert [r["attempt"] for r in runs] == [1, 0]
        dut = api.get(f"/api/duts/{serials['s3']}").json()
        assert (dut["attempts"], dut["n_runs"], dut["attempt"], dut["verdict"]) == (1, 2, 1, s3["verdict"]), dut
        y = httpx.get(f"{live.url}/api/yield", headers=auth("mes")).json()
        verdicts = {k: [by[k]["verdict"]] for k in ("s1", "s2")}
        verdicts["s3"] = []
        for s in st2["slots"]:
            verdicts[s["slot"]].append(s["verdict"])
        assert y["duts"] == 3 and y["attempts"] == sum(len(v) for v in verdicts.values()), (y, verdicts)
        assert y["first_pass"] == sum(v[0] == "pass" for v in verdicts.values()), (y, verdicts)
        assert y["final_pass"] == sum(v[-1] == "pass" for v in verdicts.values()), (y, verdicts)

        # the rows in the file: attempt 0 for the mismatch, 1 for the run that tested the part
        con = sqlite3.connect(live.db_path)
        rows = con.execute("SELECT r.batch_id, r.attempt, r.label_serial, r.verdict FROM dut_run r JOIN dut d ON "
                           "d.id = r.dut_id WHERE d.serial = ? ORDER BY r.id", (serials["s3"],)).fetchall()
        con.close()
        assert rows == [(bid, 0, "SIM9999", "error"), (bid2, 1, serials["s3"], s3["verdict"])]
        audit = httpx.get(f"{live.url}/api/audit", headers=auth("admin")).json()
        start = next(a for a in audit if a["action"] == "batch.start" and a["target"] == f"batch {bid2}")
        assert start["actor"] == "Bo" and start["detail"]["via"].endswith(f"(retest of batch {bid})")
        assert start["detail"]["labels"] == {"s3": serials["s3"]}


def test_a_faulted_slot_whose_board_answers_is_ready_again_and_a_gone_one_is_offered(tmp_path, request):
    with LiveStation(tmp_path, n_serial=3, n_can=0, speed=200.0, fixture=True) as live, \
            httpx.Client(base_url=live.url, timeout=30, headers={**auth("operator"), "X-Operator": "Ana"}) as api:
        # "hold" (logs data, no verdict) runs until aborted: s2's label is wrong (faulted, its board
        # answers); s3's board goes away
        r = api.post("/api/batches", json={"profile": "hold", "operator": "Ana", "labels": {"s2": "WRONG-2"}})
        assert r.status_code == 201, r.text
        bid = r.json()["id"]
        _wait(api, bid, lambda s: {x["slot"]: x["state"] for x in s["slots"]}.get("s3") == "running", 30, "s3 running")
        # the gone board's pty number must stay taken (a slave held open here): once freed, the
        # kernel hands it to the next pty on this machine (another test's board), which the next
        # batch's retry of s3 would then open and take from that test
        held = os.open(live.sim.serial_ports[2], os.O_RDWR | os.O_NOCTTY)
        request.addfinalizer(lambda: os.close(held))
        live.call(live.sim.board(2).disconnect)
        st = _wait(api, bid, lambda s: {x["slot"]: x["state"] for x in s["slots"]}.get("s3") == "faulted", 30,
                   "s3's link lost")
        during = _slots(api)  # inside the running batch: each slot shows its run
        assert during["s2"]["state"] == "faulted" and during["s3"]["state"] == "faulted"
        assert during["s1"]["state"] == "busy"
        assert api.post(f"/api/batches/{bid}/abort").status_code == 200
        st = _wait(api, bid, lambda s: s["state"] in ENDED, 30, "the abort")
        by = {s["slot"]: s for s in st["slots"]}
        assert "label serial 'WRONG-2'" in by["s2"]["error"] and "link lost" in by["s3"]["error"]
        assert by["s1"]["state"] == "interrupted" and by["s2"]["state"] == by["s3"]["state"] == "faulted"

        after = _slots(api)
        assert after["s1"]["state"] == "identified" and after["s1"]["fault_reason"] == ""
        assert after["s2"]["state"] == "identified" and after["s2"]["fault_reason"] == ""  # its board answered
        assert after["s3"]["state"] == "faulted" and "link lost" in after["s3"]["fault_reason"]  # gone: says why
        # the runs keep their own faults and reasons
        runs = {r["slot"]: r for r in api.get(f"/api/batches/{bid}").json()["slots"]}
        assert runs["s2"]["state"] == "faulted" and "label serial 'WRONG-2'" in runs["s2"]["error"]
        assert runs["s3"]["state"] == "faulted" and "link lost" in runs["s3"]["error"]

        # the next batch may take every slot: s1 and s2 run, s3's connect is tried again and says why
        r = api.post("/api/batches", json={"profile": "hold", "operator": "Ana", "slots": ["s1", "s2", "s3"]})
        assert r.status_code == 201, r.text
        bid2 = r.json()["id"]

        def connected(s):
            states = {x["slot"]: x["state"] for x in s["slots"]}
            return states.get("s1") == "running" and states.get("s2") == "running" and states.get("s3") == "faulted"

        st2 = _wait(api, bid2, connected, 30, "s1, s2 running and s3 tried")
        s3 = next(x for x in st2["slots"] if x["slot"] == "s3")
        assert s3["error"] and s3.get("run_id") is None  # its reason; no board answered: no run, no attempt
        assert api.post(f"/api/batches/{bid2}/abort").status_code == 200
        _wait(api, bid2, lambda s: s["state"] in ENDED, 30, "the abort")
        after = _slots(api)
        assert after["s2"]["state"] == "identified" and after["s3"]["state"] == "faulted" and after["s3"]["fault_reason"]


# ---- retest_batch's rules, on a stand-in station (the start itself is the daemon's start_batch) ----

def _empty_db(folder):
    """A real station database holding no batch: where a retest looks for a batch this daemon
    did not run (station/daemon/batches.py ended_batch)."""
    from db.database import Database

    db = Database(f"sqlite:///{folder / 'empty.db'}")
    db.upgrade()
    return db


def _station(verdicts: dict, labels: dict | None = None, boards: dict | None = None, state: str = "finished",
             db=None):
    boards = boards or {}
    duts = [NS(slot=k, verdict={"verdict": v} if v else None, label_serial=(labels or {}).get(k),
               serial=boards.get(k, f"SN-{k}"), identity=object()) for k, v in verdicts.items()]
    seq = NS(state=state, duts=duts, trace=Trace(work_order="WO-1", lot="L1", labels=dict(labels or {})),
             profile=NS(name="fast-thermal"))
    return _desk({7: seq}, list(verdicts), db)


def _desk(batches: dict, slots: list, db):
    """A real BatchDesk on stand-in parts: the retest reads only its batches, slots and database."""
    from contracts.events import EventBus
    from station.daemon.batches import BatchDesk

    desk = BatchDesk(db=db, bus=EventBus(), slots=NS(slots={k: None for k in slots}), storage=None, profiles={},
                     config=None, calibrator_factory=lambda: None, running=lambda: True)
    desk.batches.update(batches)
    return desk


@pytest.fixture
def started(monkeypatch):
    import station.daemon.batches as batches

    calls = []
    monkeypatch.setattr(batches.BatchDesk, "start_batch", lambda st, profile, slots, operator, trace, by="": (
        calls.append(NS(profile=profile, slots=slots, operator=operator, trace=trace, by=by)) or 8))
    return calls


def test_retest_takes_error_fail_and_marginal_never_pass(started, tmp_path):
    from station.daemon.batches import BatchDesk

    retest_batch = BatchDesk.retest_batch

    st = _station({"a": "pass", "b": "marginal", "c": "fail", "d": "error", "e": None})
    assert retest_batch(st, 7, "Bo") == 8
    (call,) = started
    assert call.slots == ["b", "c", "d"] and call.operator == "Bo" and call.profile == "fast-thermal"
    assert (call.trace.work_order, call.trace.lot, call.trace.labels) == ("WO-1", "L1", {})
    assert call.by == "station (retest of batch 7)"
    with pytest.raises(ValueError, match="no slot that ended error, fail or marginal"):
        retest_batch(_station({"a": "pass"}), 7, "Bo")
    with pytest.raises(ValueError, match="still logging"):
        retest_batch(_station({"a": "fail"}, state="logging"), 7, "Bo")
    db = _empty_db(tmp_path)
    with pytest.raises(KeyError):  # neither this daemon's nor in its database
        retest_batch(_station({"a": "fail"}, db=db), 9, "Bo")
    db.dispose()


def test_retest_labels_are_scanned_again_and_a_contradicted_label_is_never_reused(started):
    from station.daemon.batches import BatchDesk

    retest_batch = BatchDesk.retest_batch

    labels = {"a": "SN-a", "b": "SIM9999", "c": "SN-c"}  # b's label is not its board's serial
    st = _station({"a": "fail", "b": "error", "c": "pass"}, labels)
    with pytest.raises(ValueError, match=r"the label scanned for b \('SIM9999'\) is not its board's serial "
                                         r"\('SN-b'\): scan the part's label again"):
        retest_batch(st, 7, "Bo")
    assert not started
    # scanned again: exactly what was scanned, trimmed; a slot without a new label runs unchecked
    retest_batch(st, 7, "Bo", labels={"b": "  SN-b "})
    assert started[-1].slots == ["a", "b"] and started[-1].trace.labels == {"b": "SN-b"}
    # no label given, none contradicted: the batch's labels of the retested slots are kept
    retest_batch(_station({"a": "fail", "c": "pass"}, {"a": "SN-a", "c": "SN-c"}), 7, "Bo")
    assert started[-1].trace.labels == {"a": "SN-a"}
    # some of the slots only; never one that passed
    retest_batch(st, 7, "Bo", labels={}, slots=["b"])
    assert started[-1].slots == ["b"] and started[-1].trace.labels == {}
    with pytest.raises(ValueError, match="c did not end error, fail or marginal"):
        retest_batch(st, 7, "Bo", labels={}, slots=["b", "c"])
