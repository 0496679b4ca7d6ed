"""The MES's route check (design 5.4): a part the MES refuses is never tested, and the site's
policy decides what happens when the MES does not answer.

End to end: simulated boards on real ptys, the lamp relay on a real Modbus server, the daemon, a
SQLite file, and the MES stand-in (drivers/sim/mes_standin.py) on real HTTP on 127.0.0.1. The
truth is the stand-in's own list of held serials and of the calls it received, the lamp's
switch-on events, and the rows in the database.
"""

from __future__ import annotations


import pytest
from hypothesis import given
from hypothesis import strategies as st

from cli.commands.demo import sim_config
from contracts.trace import Trace
from db.repository import audit_list, batch_detail, results_since
from drivers.sim.mes_standin import MesStandIn
from drivers.sim.station_sim import SimStation
from station.config import parse_config
from station.daemon.storage import open_database
from station.daemon.supervisor import Station
from station.decisions.route_check import RoutePart, may_test, read_answer, request_for
from station.records.causes import cause_of

HOLD = "on quality hold: NCR-2291 (voids under U3)"
SPEED = 400.0


def _read(status: int, body: bytes) -> str:
    return read_answer(status, body, allowed_field="allowed", reason_field="reason",
                       refuse_statuses=[403, 409, 423]).outcome


def test_the_answer_rules():
    assert _read(200, b'{"allowed": true}') == "allowed"
    assert _read(200, b'{"allowed": "YES"}') == "allowed"
    assert _read(200, b'{"allowed": false, "reason": "hold"}') == "refused"
    assert _read(200, b'{"allowed": "hold"}') == "refused"
    assert _read(403, b"") == "refused"  # a refusal status whatever the body
    assert _read(423, b'{"allowed": true}') == "refused"
    # no usable answer is never a yes: the policy decides
    for status, body in ((200, b'{"allowed": 1}'), (200, b"<html/>"), (200, b""), (200, b'{"ok": true}'),
                         (500, b'{"allowed": true}'), (404, b""), (302, b""), (200, b'{"allowed": null}')):
        assert _read(status, body) == "unanswered", (status, body)
    nested = read_answer(200, b'{"route": {"ok": "no", "why": "retest limit \\u0007 reached\\n"}}',
                         allowed_field="route.ok", reason_field="route.why", refuse_statuses=[])
    assert (nested.outcome, nested.reason) == ("refused", "retest limit reached")


@given(st.binary(max_size=200), st.integers(min_value=100, max_value=599))
def test_no_answer_is_read_as_a_yes_unless_it_says_yes(body, status):
    out = _read(status, body)
    if out == "allowed":
        assert 200 <= status < 300 and status not in (403, 409, 423)
        assert b"allowed" in body


def test_the_url_quotes_the_part():
    part = RoutePart(serial="A+B/1&x=2", slot="s01", operation="thermal cal", station="st 1")
    req = request_for("http://mes/route/{serial}?op={operation}&st={station}", "GET", part)
    assert req.url == "http://mes/route/A%2BB%2F1%26x%3D2?op=thermal%20cal&st=st%201" and req.json_body is None
    with pytest.raises(ValueError, match="nope"):
        request_for("http://mes/{nope}", "GET", part)
    assert request_for("http://mes/route", "POST", part).json_body == part.fields()


def test_the_policy():
    from station.decisions.route_check import RouteAnswer

    for outcome, refuse, flag in (("allowed", True, True), ("refused", False, False), ("unanswered", False, True)):
        a = RouteAnswer(outcome, "")  # type: ignore[arg-type]
        assert (may_test(a, "refuse"), may_test(a, "proceed_and_flag")) == (refuse, flag)


async def _run_batch(tmp_path, sim, mes_url: str, policy: str, timeout_s: float = 2.0):
    route = {"url": mes_url, "when_unanswered": policy, "timeout_s": timeout_s}
    cfg = parse_config(sim_config(sim, speed=SPEED, db_url=f"sqlite:///{tmp_path / 'station.db'}",
                                  route_check=route), "<test>")
    db = open_database(cfg.database_url)
    station = Station(cfg, db=db)
    await station.start()
    try:
        events = station.bus.subscribe(maxsize=1_000_000)
        bid = station.start_batch("fast-thermal", None, "pytest", trace=Trace(work_order="WO-7"))
        status = await station.wait_batch(bid, timeout_s=240)
        await station.flush_db()
        seen = []
        while not events.empty():
            seen.append(events.get_nowait())
        return status, db, seen, bid
    finally:
        await station.close()


def _order(seen) -> tuple[int | None, dict[str, int]]:
    """Index of the lamp's first switch-on, and of each slot's fault, in the event stream."""
    lamp_on = next((i for i, e in enumerate(seen) if e.kind == "LampChanged" and e.on), None)
    faults = {e.slot: i for i, e in enumerate(seen) if e.kind == "SlotStateChanged" and e.state == "faulted"}
    return lamp_on, faults


@pytest.mark.slow
@pytest.mark.timeout(300)
async def test_the_mes_refuses_one_serial_that_slot_is_never_tested_the_others_pass(tmp_path):
    async with SimStation(n_serial=3, n_can=0, seed=21, speed=SPEED) as sim:
        held = sim.truths[1].serial
        with MesStandIn({held.lower(): HOLD}) as mes:  # the MES compares serials case-insensitively
            status, db, seen, bid = await _run_batch(tmp_path, sim, mes.url, "refuse")
            try:
                assert status["state"] == "finished", status["error"]
                # the MES was asked once per board, about the board's own serial, before any heat
                asked = sorted(c.fields["serial"] for c in mes.calls)
                assert asked == sorted(t.serial for t in sim.truths)
                assert all(c.fields["operation"] == "thermal-calibration" and c.fields["work_order"] == "WO-7"
                           for c in mes.calls)
                by_slot = {s["slot"]: s for s in status["slots"]}
                assert by_slot["s02"]["serial"] == held
                assert by_slot["s02"]["state"] == "faulted" and HOLD in by_slot["s02"]["fault_reason"]
                assert by_slot["s02"]["samples"] == 0  # its board never streamed
                verdicts = {s: (v.get("decision") or {}).get("verdict") for s, v in by_slot.items()}
                assert verdicts == {"s01": "pass", "s02": "error", "s03": "pass"}, {
                    s: by_slot[s]["fault_reason"] or (by_slot[s].get("decision") or {}).get("reason") for s in by_slot}
                lamp_on, faults = _order(seen)
                assert lamp_on is not None and faults["s02"] < lamp_on  # stopped before the lamp first heated
                assert set(faults) == {"s02"}
                # the record says why, and the refused part is no attempt of its serial
                runs = {r["slot"]: r for r in batch_detail(db, bid)["runs"]}
                assert runs["s02"]["route_check"] == "refused" and runs["s02"]["route_reason"] == HOLD
                assert runs["s02"]["attempt"] == 0 and runs["s02"]["n_samples"] == 0
                assert "faulted: MES route check: the MES refused" in runs["s02"]["reason"]
                assert cause_of(runs["s02"]["fault_reason"]) == "route refused (MES)"
                assert {runs[s]["route_check"] for s in ("s01", "s03")} == {"allowed"}
                assert all(runs[s]["attempt"] == 1 for s in ("s01", "s03"))
                # the MES receives the refusal in its feed, with the MES's own words
                feed = {r["slot"]: r for r in results_since(db, 0, 100)}
                assert feed["s02"]["route_check"] == "refused" and feed["s02"]["verdict"] == "error"
                # every call audited, with its outcome
                checks = [a for a in audit_list(db, 100) if a["action"] == "route.check"]
                assert sorted((a["detail"]["serial"], a["detail"]["outcome"]) for a in checks) == sorted(
                    (t.serial, "refused" if t.serial == held else "allowed") for t in sim.truths)
            finally:
                db.dispose()


@pytest.mark.slow
@pytest.mark.timeout(200)
@pytest.mark.parametrize("how", ["down", "slow", "error"])
async def test_mes_not_answering_with_policy_refuse_tests_nothing_and_never_heats(tmp_path, how):
    async with SimStation(n_serial=2, n_can=0, seed=22, speed=SPEED) as sim:
        mes = MesStandIn(slow_s=5.0).start()
        url = mes.url
        if how == "down":
            mes.stop()
        else:
            mes.mode = "slow" if how == "slow" else "error"
        try:
            status, db, seen, bid = await _run_batch(tmp_path, sim, url, "refuse", timeout_s=1.0)
        finally:
            if how != "down":
                mes.stop()
        try:
            assert status["state"] == "failed"
            assert not any(e.kind == "LampChanged" and e.on for e in seen)  # the lamp never switched on
            runs = batch_detail(db, bid)["runs"]
            assert len(runs) == 2
            for r in runs:
                assert r["route_check"] == "unanswered" and r["attempt"] == 0 and r["n_samples"] == 0
                assert "the MES did not answer" in r["fault_reason"] and "'refuse'" in r["fault_reason"]
                assert cause_of(r["fault_reason"]) == "MES did not answer"
                assert r["verdict"] == "error"
            checks = [a["detail"] for a in audit_list(db, 100) if a["action"] == "route.check"]
            assert len(checks) == 2 and all(c["outcome"] == "unanswered" and c["policy"] == "refuse" for c in checks)
            if how == "slow":
                assert all(0.9 <= float(c["elapsed_s"]) < 3.0 for c in checks), checks  # its timeout, not the MES's 5 s
        finally:
            db.dispose()


@pytest.mark.slow
@pytest.mark.timeout(300)
async def test_mes_down_with_policy_proceed_and_flag_tests_and_flags(tmp_path):
    async with SimStation(n_serial=2, n_can=0, seed=23, speed=SPEED) as sim:
        mes = MesStandIn().start()
        url = mes.url
        mes.stop()  # the MES is down for the whole batch
        status, db, seen, bid = await _run_batch(tmp_path, sim, url, "proceed_and_flag")
        try:
            assert status["state"] == "finished", status["error"]
            for s in status["slots"]:
                assert s["state"] == "done" and s["samples"] > 0
                assert (s.get("decision") or {}).get("verdict") == "pass", s.get("decision")
                assert "not route-checked" in s["route_flag"] and "proceed_and_flag" in s["route_flag"]
            runs = batch_detail(db, bid)["runs"]
            assert all(r["route_check"] == "unanswered" and r["attempt"] == 1 for r in runs)
            assert all("ConnectError" in r["route_reason"] for r in runs)
            # the MES learns the part was tested without its yes
            feed = results_since(db, 0, 100)
            assert len(feed) == 2 and all(r["route_check"] == "unanswered" for r in feed)
            checks = [a["detail"] for a in audit_list(db, 100) if a["action"] == "route.check"]
            assert len(checks) == 2 and all(c["policy"] == "proceed_and_flag" for c in checks)
        finally:
            db.dispose()


def test_no_route_check_configured_asks_nobody():
    cfg = parse_config({"slots": [{"name": "s01", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1}},
                       "<test>")
    assert cfg.mes.route_check is None


def test_route_check_config_errors_name_the_key():
    from contracts.types import StationError

    base = {"slots": [{"name": "s01", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1}}
    with pytest.raises(StationError, match="route_check.*when_unanswered"):
        parse_config({**base, "mes": {"route_check": {"url": "http://x", "when_unanswered": "maybe"}}}, "<t>")
    with pytest.raises(StationError, match="refuse_statuses"):
        parse_config({**base, "mes": {"route_check": {"url": "http://x", "refuse_statuses": [200]}}}, "<t>")


