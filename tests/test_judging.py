"""station/decisions/moment.py: the hooks between the daemon and the verdicts, on the VerdictContext the
Station builds (station/decisions/verdict_context.py) with a real (temporary SQLite) database and a real
EventBus (no hardware needed: the hooks read only the DUT runs, the config and the database)."""

from __future__ import annotations

from types import SimpleNamespace

from station.config import parse_config
from contracts.events import EventBus
from contracts.run_records import ProgramRecord, ThermalReport
from station.profiles import all_profiles
from station.daemon.dut_run import DutRun
from station.daemon.progress import time_left
from station.daemon.storage import open_database
from station.decisions.moment import judge_final
from contracts.trace import Trace
from contracts.types import Identity
from station.decisions.verdict_context import VerdictContext

CFG = parse_config({"slots": [{"name": "s1", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1},
                    "products": {"LIS3DSH": {"sensor": "LIS3DSH", "version": "4", "limits": [
                        {"measurement": "tdsf_ppm_per_c", "low": -500, "unit": "ppm/C", "label": "TDSF", "required": True},
                        {"measurement": "verified_drift_error_fs_pct", "high": 1.0, "unit": "%FS", "label": "verified E_FS",
                         "analysis": "any"}]}}}, "t")


def station_and_batch(n: int = 2, ending: str = "finished"):
    db = open_database(None)  # no URL: a temporary SQLite file, the station's own storage path
    batch_id = db.create_batch("fast-thermal", "op", {})
    bus = EventBus()
    q = bus.subscribe()
    st = VerdictContext(db=db, bus=bus, product_for=CFG.product_for, profiles=all_profiles(CFG))
    duts = []
    for i in range(n):
        d = DutRun(slot=f"s{i + 1}", identity=Identity(serial=f"SER{i}", sensor="LIS3DSH"), state="running")
        d.run_id = db.create_run(batch_id, d.slot, d.serial)
        d.attempt = db.run_attempt(d.run_id)  # as slots.connect_duts reads it when the run is made
        d.n_samples = 1000
        d.result = ThermalReport.from_json({
            "axes": {ax: {"tdb_mg_per_c": 0.1, "tdsf_ppm_per_c": -100.0, "tdsf_sigma_ppm_per_c": 1.0} for ax in "xyz"},
            "residual": {"axes": {ax: {"drift_error_fs_pct": 0.3, "drift_error_fs_sigma_pct": 0.02, "bow_mg": 0.5,
                                       "bow_sigma_mg": 0.2} for ax in "xyz"}}})
        duts.append(d)
    seq = SimpleNamespace(batch_id=batch_id, profile=all_profiles(CFG)["fast-thermal"], duts=duts, ending=ending, state="analysing",
                          error="", trace=Trace())
    return st, seq, q


def events(q):
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


def test_each_run_is_judged_once_at_the_end_from_its_final_state():
    st, seq, q = station_and_batch()
    d1, d2 = seq.duts
    d1.state = "done"
    d2.state, d2.fault_reason = "faulted", "serial /dev/pts/9: link lost"
    judge_final(st, seq)
    assert (d1.verdict["verdict"], d1.verdict["attempt"], d1.verdict["limits_version"]) == ("pass", 1, "4")
    assert d2.verdict["verdict"] == "error" and "link lost" in d2.verdict["reason"]
    evs = events(q)
    assert [(type(e).__name__, e.slot) for e in evs] == [("DutVerdict", "s1"), ("DutVerdict", "s2")]
    judge_final(st, seq)  # released once: a second call sends no second record
    assert events(q) == []


def test_a_verified_profile_requires_crc_compensation_and_verified_figures():
    st, seq, q = station_and_batch(n=3)
    seq.profile = all_profiles(CFG)["fast-thermal-verified"]
    good_program = {"programmed": True, "crc": "1A2B3C4D", "readback_crc": "1A2B3C4D", "readback_identical": True,
                    "comp": True}
    verified = {"passed": True, "e_after_fs_pct": {a: 0.1 for a in "xyz"}, "e_after_fs_sigma_pct": {a: 0.02 for a in "xyz"},
                "axes": {a: {"passed": True} for a in "xyz"}}
    ok, bad_crc, unverified = seq.duts
    for d in seq.duts:
        d.state = "done"
    ok.program, ok.verification = ProgramRecord.from_json(good_program), verified
    bad_crc.program = ProgramRecord.from_json(dict(good_program, readback_crc="00000000"))
    bad_crc.verification = verified
    unverified.program = ProgramRecord.from_json(good_program)  # e.g. the verification heat never produced its figures
    judge_final(st, seq)
    assert ok.verdict["verdict"] == "pass", ok.verdict["reasons"]
    assert bad_crc.verdict["verdict"] == "fail" and "readback CRC" in bad_crc.verdict["reason"]
    assert unverified.verdict["verdict"] == "error"
    assert "verified E_FS not measured" in unverified.verdict["reason"]
    # resumed after its program step: no programming record in this run -> error, the cause first
    st, seq, q = station_and_batch(n=1)
    seq.profile = all_profiles(CFG)["fast-thermal-verified"]
    seq.duts[0].state = "done"
    judge_final(st, seq)
    v = seq.duts[0].verdict
    assert v["verdict"] == "error" and v["reasons"][0].startswith("not programmed: no programming record")


def test_aborted_and_interrupted_batches_give_error_naming_the_end():
    st, seq, q = station_and_batch(ending="aborted")
    seq.error = "operator"
    for d in seq.duts:
        d.state, d.fault_reason = "interrupted", "batch aborted: operator"
    judge_final(st, seq)
    assert all(d.verdict["verdict"] == "error" and "batch aborted: operator" in d.verdict["reason"] for d in seq.duts)
    st, seq, q = station_and_batch(ending="interrupted")
    seq.error = "daemon shutdown"
    seq.duts[0].state = "interrupted"
    seq.duts[1].state, seq.duts[1].fault_reason = "faulted", "no samples for 10 s"
    judge_final(st, seq)
    # the run ended here (a resumed batch judges it again: a new record that supersedes this one)
    assert seq.duts[0].verdict["verdict"] == "error" and "resumable" in seq.duts[0].verdict["reason"]
    assert seq.duts[1].verdict["verdict"] == "error" and "no samples" in seq.duts[1].verdict["reason"]
    assert len(events(q)) == 2


def test_retest_attempt():
    st, seq, q = station_and_batch(n=1)
    d = seq.duts[0]
    retest = st.db.create_batch("fast-thermal", "op", {})
    d.run_id = st.db.create_run(retest, "s1", d.serial)  # the same serial seen again
    d.attempt = st.db.run_attempt(d.run_id)
    d.state = "done"
    judge_final(st, seq)
    assert d.verdict["attempt"] == 2


def test_time_left_is_zero_after_the_end_and_capped_by_timeouts():
    st, seq, q = station_and_batch()
    seq.state = "finished"
    seq.step = None
    assert time_left(SimpleNamespace(config=CFG), seq)["batch_s"] == 0.0


class _DatabaseDown:
    """A database that answers nothing (a PostgreSQL restart, a hung server): every call raises."""

    def __getattr__(self, name):
        def down(*args, **kwargs):
            raise ConnectionError(f"database down ({name})")
        return down


def test_judging_at_the_end_needs_no_database():
    """Issue 37: one connection error at the end used to leave every run of the batch without a
    verdict. Judging reads only the run's own state (its attempt was read when it was made)."""
    import dataclasses

    st, seq, q = station_and_batch()
    down = dataclasses.replace(st, db=_DatabaseDown())
    d1, d2 = seq.duts
    d1.state, d2.state = "done", "done"
    judge_final(down, seq)
    verdicts = [e for e in events(q) if e.kind == "DutVerdict"]
    assert [(e.slot, e.verdict["verdict"], e.verdict["attempt"]) for e in verdicts] == [("s1", "pass", 1), ("s2", "pass", 1)]


def test_a_run_that_ended_with_no_verdict_stored_is_judged_error_at_the_next_start():
    """Every run that ended gets exactly one final record: one whose verdict was lost (its disk
    failed with the journal's) is judged error at the next start; a judged run, a run older than
    verdicts (no software_version) and a replay's run are left alone."""
    from db.models import MeasuredBy
    from station.decisions.moment import judge_unjudged_runs

    db = open_database(None)
    bus = EventBus()
    q = bus.subscribe()
    ctx = VerdictContext(db=db, bus=bus, product_for=CFG.product_for, profiles=all_profiles(CFG))
    bid = db.create_batch("fast-thermal", "op", {})
    ours = MeasuredBy(software_version="1.0")
    lost = db.create_run(bid, "s1", "LOST1", "LIS3DSH", {}, measured_by=ours)
    judged = db.create_run(bid, "s2", "JUDGED1", "LIS3DSH", {}, measured_by=ours)
    old = db.create_run(bid, "s3", "OLD1", "LIS3DSH", {})  # made before runs carried their software
    for r in (lost, judged, old):
        db.set_run_state(r, "done")
    db.set_batch_state(bid, "finished")
    from sqlalchemy import update

    from db.models import DutRun as RunRow
    with db.session() as s:
        s.execute(update(RunRow).where(RunRow.id == judged).values(verdict="pass"))
    replay = db.create_batch("fast-thermal", "op", {}, replay_of="logs")
    db.set_run_state(db.create_run(replay, "s1", "LOST1", "LIS3DSH", {}, measured_by=ours), "done")
    db.set_batch_state(replay, "finished")
    assert judge_unjudged_runs(ctx, []) == 1
    (ev,) = [e for e in events(q) if e.kind == "DutVerdict"]
    assert ev.serial == "LOST1" and ev.verdict["verdict"] == "error" and ev.verdict["run_id"] == lost
    assert "not stored before the station stopped" in ev.verdict["reason"]
    assert judge_unjudged_runs(ctx, [bid]) == 0  # the batches this start marked interrupted are judged there
