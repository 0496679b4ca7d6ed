"""station/judging.py: the hooks between the daemon and the verdicts, on a Station-shaped object with
the in-memory database stand-in and a real EventBus (no hardware needed: the hooks read only the
DUT runs, the config and the database)."""

from __future__ import annotations

from types import SimpleNamespace

from station.config import parse_config
from station.events import DutVerdict, EventBus
from station.profiles import all_profiles
from station.sequencer import DutRun
from station.supervisor import MemoryDb
from station.judging import judge_result, judge_unjudged, rejudge, time_left
from station.types import Identity
from station.verdicts import Measurement

CFG = parse_config({"slots": [{"name": "s1", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1},
                    "products": {"LIS3DSH": {"sensor": "LIS3DSH", "version": "4", "limits": [
                        {"measurement": "tdsf_ppm_per_c", "low": -500, "unit": "ppm/C", "label": "TDSF", "required": True},
                        {"measurement": "verified_drift_error_fs_pct", "high": 1.0, "unit": "%FS", "label": "verified E_FS",
                         "analysis": "any"}]}}}, "t")


def station_and_batch(n: int = 2, ending: str = "finished"):
    db = MemoryDb()
    bus = EventBus()
    q = bus.subscribe()
    st = SimpleNamespace(config=CFG, db=db, bus=bus, slots={})
    duts = []
    for i in range(n):
        d = DutRun(slot=f"s{i + 1}", identity=Identity(serial=f"SER{i}", sensor="LIS3DSH"), state="running")
        d.run_id = db.create_run(1, d.slot, d.serial)
        d.n_samples = 1000
        d.result = {"axes": {ax: {"tdb_mg_per_c": 0.1, "tdsf_ppm_per_c": -100.0, "tdsf_sigma_ppm_per_c": 1.0} for ax in "xyz"}}
        duts.append(d)
    seq = SimpleNamespace(batch_id=1, profile=all_profiles(CFG)["fast-thermal"], duts=duts, ending=ending, state="analysing",
                          error="")
    return st, seq, q


def events(q):
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


def test_result_then_a_faulted_dut_then_a_verified_error():
    st, seq, q = station_and_batch()
    d1, d2 = seq.duts
    v = judge_result(st, seq, d1)
    assert (v["verdict"], v["attempt"], v["limits_version"]) == ("pass", 1, "4")
    d2.state, d2.fault_reason = "faulted", "serial /dev/pts/9: link lost"
    judge_unjudged(st, seq)
    assert d2.verdict["verdict"] == "error" and "link lost" in d2.verdict["reason"]
    evs = events(q)
    assert [type(e).__name__ for e in evs] == ["DutVerdict"] and evs[0].slot == "s2"
    # program-and-verify adds the verified drift error of the compensated output: judged again
    v = rejudge(st, seq, d1, [Measurement("verified_drift_error_fs_pct", 1.3, "%FS", "z", 0.02)])
    assert v["verdict"] == "fail" and v["reason"] == "z verified E_FS 1.3 %FS, limit 1"
    assert isinstance(events(q)[0], DutVerdict)


def test_aborted_batch_gives_error_and_interrupted_batch_waits():
    st, seq, q = station_and_batch(ending="aborted")
    seq.error = "operator"
    for d in seq.duts:
        d.state = "interrupted"
    judge_unjudged(st, seq)
    assert all(d.verdict["verdict"] == "error" and "batch aborted: operator" in d.verdict["reason"] for d in seq.duts)
    st, seq, q = station_and_batch(ending="interrupted")
    seq.duts[0].state = "interrupted"
    seq.duts[1].state, seq.duts[1].fault_reason = "faulted", "no samples for 10 s"
    judge_unjudged(st, seq)
    assert seq.duts[0].verdict is None  # resumable: not over
    assert seq.duts[1].verdict["verdict"] == "error"


def test_retest_attempt_in_memory():
    st, seq, q = station_and_batch(n=1)
    d = seq.duts[0]
    d.run_id = st.db.create_run(2, "s1", d.serial)  # the same serial seen again
    assert judge_result(st, seq, d)["attempt"] == 2


def test_time_left_is_zero_after_the_end_and_capped_by_timeouts():
    st, seq, q = station_and_batch()
    seq.state = "finished"
    seq.step = None
    assert time_left(st, seq)["batch_s"] == 0.0
