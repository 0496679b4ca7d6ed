"""A station given more than it can follow says so, counts what it lost, and faults no healthy part.

Real parts: serial boards on pseudo-terminals (a plant that never waits for the station, as real
boards do not, with a board's small transmit buffer: what does not fit is lost, a sequence gap),
the daemon, the Modbus lamp, SQLite on disk. The station's PC is made too slow by a throttled
intake: every sample costs it CPU time (a busy loop inside the event loop, exactly what slow
parsing does) for a few seconds of one step. The independent truth is the simulated boards' own
count of the bytes they could not send.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from test_daemon_e2e import wait_for
from drivers.modbus_devices import ModbusLampRelay, ModbusLink
from station.config import parse_config
from station.daemon import intake
from station.daemon.intake_monitor import BIG_READ_SAMPLES, READS_PER_S, IntakeMonitor, read_pace_s
from station.daemon.storage import open_database
from station.daemon.supervisor import Station

ROOT = Path(__file__).resolve().parents[1]

SPEED = 100.0


def test_many_links_are_each_read_less_often_so_the_loop_stays_free():
    """Up to 25 links keep the configured period; beyond, links whose reads are small are read so
    that all together read 250 times a second (the loop's cost is per read: design 2.2); a link
    whose reads are big already keeps the period; the pace follows the pumps that run."""
    assert read_pace_s(0.1, 1) == 0.1 and read_pace_s(0.1, 25) == 0.1
    assert read_pace_s(0.1, 64) == pytest.approx(64 / READS_PER_S) == pytest.approx(0.256)
    x60 = 3.125 * 60  # a board's samples per wall second at x60: 19 a read at 0.1 s
    assert read_pace_s(0.1, 64, x60) == pytest.approx(0.256)
    big = BIG_READ_SAMPLES / 0.1  # a fast board (or a replay): its reads are big at 0.1 s
    assert read_pace_s(0.1, 64, big) == 0.1 and read_pace_s(0.1, 64, 0.99 * big) == pytest.approx(0.256)
    assert read_pace_s(0.5, 64) == 0.5  # a longer configured period is kept
    mon = IntakeMonitor()
    for k in range(64):
        mon.pumping.add(f"s{k}")
    assert 64 / mon.pace_s(0.1) == pytest.approx(READS_PER_S)  # reads per second, all links
    for k in range(48):
        mon.pumping.discard(f"s{k}")
    assert mon.pace_s(0.1) == 0.1
    from station.config import Timing
    from station.replay.runner import REPLAY_READS_PER_S

    assert Timing().reads_per_s == READS_PER_S  # the station's budget, configurable
    replay = IntakeMonitor(reads_per_s=REPLAY_READS_PER_S)  # a replay's world waits on the station
    replay.pumping.update(f"s{k}" for k in range(64))
    assert replay.pace_s(0.1, x60) == 0.1


def test_the_monitor_tells_the_stations_loss_from_the_links():
    """Pure core: a gap while the station keeps up is the link's; a gap while it runs behind its
    link, or while its CPU is saturated, is the station's; the alarm says so in words and clears
    with hysteresis; a batch beyond its capacity is refused with the numbers."""
    cpu = [0.0]
    m = IntakeMonitor(speed=10.0, cost_us_per_sample=10.0, cpu_clock=lambda: cpu[0])
    for k in range(40):  # 31 samples per read, a few waiting: the station keeps up
        cpu[0] = 0.01 * k
        assert m.note_block("s01", 0.1 * k, 3, 31, 0, 3.125) == 0
    assert m.behind_s("s01") == pytest.approx(3 / 31.25)
    assert m.note_block("s01", 4.0, 3, 31, 7, 3.125) == 0  # on time, idle CPU: the link's gap
    assert m.state(4.0).alarm is None and m.links["s01"].lost_link == 7
    # 78 samples wait in its queues: at 3.125 Hz x10 that is 2.5 s of the board's sending
    assert m.note_block("s01", 7.0, 78, 31, 0, 3.125) == 0
    assert m.behind_s("s01") == pytest.approx(2.5, abs=0.01)
    assert m.note_block("s01", 7.5, 95, 31, 12, 3.125) == 12  # then the link shows a gap: ours
    st = m.state(7.5)
    assert st.lost_station == 12 and st.lost_by_slot == {"s01": 12}
    assert st.alarm is not None and "lost to the station's backlog" in st.alarm, st.alarm
    # caught up, but the alarm holds for ALARM_HOLD_S after a loss, then clears
    m.note_block("s01", 8.0, 2, 31, 0, 3.125)
    assert m.state(20.0).alarm is not None
    m.note_block("s01", 40.0, 2, 31, 0, 3.125)
    assert m.behind_s("s01") < 0.1 and m.state(40.0).alarm is None
    # a gap after a read that came late (the loop was held up) is ours too, however short the queue
    assert m.note_block("s01", 41.0, 2, 31, 4, 3.125, loop_late_s=0.8) == 4
    # 100 samples waiting (3.2 s): the alarm, in words, with how far behind
    m.note_block("s01", 80.0, 100, 31, 0, 3.125)
    words = m.state(80.0).alarm
    assert words is not None and words.startswith("station behind by 3 s"), words
    # a saturated process (CPU 0.95 s per wall second over a window): a gap is the station's
    m2 = IntakeMonitor(speed=10.0, cost_us_per_sample=5000.0, cpu_clock=lambda: cpu[0])
    for k in range(60):
        wall, cpu[0] = 0.1 * k, 0.095 * k
        m2.note_block("s02", wall, 0, 31, 0, 3.125)
    assert m2.saturated
    assert m2.note_block("s02", 6.0, 0, 31, 5, 3.125) == 5
    # capacity: measured cost 0.095 s / (31 samples per 0.1 s) ~ 3.1 ms/sample -> ~260 samples/s
    assert m2.cost_us_per_sample == pytest.approx(0.095 / 31 * 1e6, rel=0.05)
    assert m2.refuse_start([3.125] * 4) is None  # 4 x 3.125 x 10 = 125 samples/s
    words = m2.refuse_start([100.0] * 8)  # 8000 samples/s
    assert words is not None and "8 DUTs at 100 Hz x10 demand 8000 samples/s" in words, words


@pytest.mark.timeout(300)
async def test_an_overloaded_station_alarms_counts_its_loss_and_faults_no_healthy_dut(tmp_path, monkeypatch):
    throttle = {"until": 0.0, "us_per_sample": 0.0}
    real_ingest = intake.ingest

    def slow_ingest(st, seq, d, block):  # type: ignore[no-untyped-def]
        if time.monotonic() < throttle["until"]:
            end = time.perf_counter() + throttle["us_per_sample"] * 1e-6 * len(block)
            while time.perf_counter() < end:  # CPU, not a sleep: the PC is too slow
                pass
        real_ingest(st, seq, d, block)

    monkeypatch.setattr(intake, "ingest", slow_ingest)
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    sim_json = tmp_path / "sim.json"
    # the plant in its own process, as real boards are: it never waits for the station, and a
    # board's transmit buffer is a real one's 4 KiB
    sim = subprocess.Popen([sys.executable, str(ROOT / "tests" / "sim_station_child.py"), str(sim_json),
                            "--serial", "4", "--can", "0", "--speed", str(SPEED), "--seed", "11", "--real-plant",
                            "--tx-buffer", "4096"], stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        assert sim.stdout is not None and sim.stdout.readline().strip() == "READY"
        spec = json.loads(sim_json.read_text())
        cfg = parse_config({**spec["config"], "database_url": f"sqlite:///{tmp_path / 'station.db'}"}, "<test>")
        db = open_database(cfg.database_url)
        st = Station(cfg, db=db)
        await st.start()
        try:
            bid = st.start_batch("fast-thermal", None, "pytest")
            await wait_for(lambda: st.batch_status(bid)["seq_state"] == "logging"
                           and st.batch_status(bid)["step_index"] >= 1, 90, "step 1 logging")
            # 4 boards x 3.125 Hz x100 = 1250 samples/s; at 1500 us each the PC would need 1.9 s per s
            throttle.update(until=time.monotonic() + 6.0, us_per_sample=1500.0)
            alarms: list[str] = []

            def alarmed() -> bool:
                a = st.intake_status()["alarm"]
                if a:
                    alarms.append(str(a))
                return bool(a)

            await wait_for(alarmed, 30, "the overload alarm")
            overload = st.batch_status(bid)["overload"]
            assert overload["alarm"] and "station" in overload["alarm"], overload
            status = await st.wait_batch(bid, timeout_s=240)
            lamp_off = await _coil_off(spec["config"])
        finally:
            await st.close()
            db.dispose()
    finally:
        sim.send_signal(signal.SIGTERM)
        sim.wait(20)
    dropped = json.loads((tmp_path / "sim.json.end").read_text())["bytes_dropped"]
    assert status["state"] == "finished", status.get("error")
    lost_any = 0
    for s in status["slots"]:
        ls = s["link_stats"]
        # no healthy DUT faulted, none failed for the samples the station lost
        assert s["state"] == "done", (s["slot"], s["fault_reason"])
        decision = s["decision"] or {}
        assert decision.get("verdict") == "pass", (s["slot"], decision.get("reason"), ls)
        # every gap is the station's: the boards lost bytes only when it did not read
        assert ls["samples_lost_station"] == ls["samples_lost"], (s["slot"], ls)
        assert (ls["samples_lost"] > 0) == (dropped[s["slot"]] > 0), (s["slot"], ls, dropped)
        lost_any += ls["samples_lost"]
    assert lost_any > 0, dropped  # the throttle did overrun the boards' buffers
    assert lamp_off


async def _coil_off(cfg: dict) -> bool:
    link = ModbusLink(cfg["lamp"]["tcp"]["host"], int(cfg["lamp"]["tcp"]["port"]))
    try:
        return not await ModbusLampRelay(link, unit=1).read_lamp()
    finally:
        await link.close()
