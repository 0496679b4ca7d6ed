"""Sequencer state machine and LampGuard, driven step by step without hardware.

The DUT side is played by a small feeder that advances each DUT's sample clock and logs segments;
the lamp relay is an in-memory coil that can be told to fail. The real links are covered by
tests/test_daemon_e2e.py.
"""

import asyncio
import math

import numpy as np
import pytest

from drivers.base import Fixture, LampRelay
from contracts.events import Alarm, EventBus, LampChanged, PromptRaised
from station.profiles import BUILTIN_PROFILES, Profile, Step
from station.daemon.safety import LampGuard, LampTripped
from station.daemon.dut_run import DutRun
from station.daemon.sequencer import Sequencer
from station.daemon.states import TRANSITIONS
from contracts.types import SampleBlock, Segment


class MemRelay(LampRelay):
    def __init__(self):
        self.coil = None
        self.writes = []
        self.fail_next = 0

    async def set_lamp(self, on):
        if self.fail_next > 0:
            self.fail_next -= 1
            raise OSError("relay does not answer")
        self.coil = on
        self.writes.append(on)

    async def read_lamp(self):
        return bool(self.coil)


class MemFixture(Fixture):
    def __init__(self):
        self.pos = 0
        self.moves = []

    async def move_to(self, position):
        self.moves.append(position)
        self.pos = position

    async def position(self):
        return self.pos

    async def moving(self):
        return False


class Hw:
    def __init__(self, bus, fixture=None, **limits):
        self.relay = MemRelay()
        kw = dict(max_on_s=1e9, max_dut_temp_c=85.0, max_plate_temp_c=90.0)
        kw.update(limits)
        self.lamp = LampGuard(self.relay, bus, retry_delays_s=(0.001, 0.002), **kw)
        self.fixture = fixture
        self.chamber = None
        self.fixture_timeout_s = 1.0
        self.plate_again_after_s = 1e9  # the feeder's boards face the position at once (no re-prompt)
        self.speed = 1.0
        self.analysed = False
        self.released = False
        self.seq = None
        self.lamp.on_trip(lambda reason: self.seq.stop("failed", f"safety trip: {reason}"))

    async def connect_duts(self, seq):
        for d in seq.duts:
            d.state = "running"

    async def release_duts(self, seq):
        self.released = True
        for d in seq.duts:
            if d.live:
                d.state = "done" if seq.ending == "finished" else "interrupted"

    def fault_dut(self, seq, d, reason):
        d.state, d.fault_reason = "faulted", reason
        seq.notify()

    async def analyse(self, seq):
        self.analysed = True


def _seg(i, t, pos):
    return Segment(i, 0, 1000, t - 300.0, t, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 25.0, 0.1, position=pos)


async def feed(seq, slow=(), dt=10.0, log_after_s=60.0):
    """Advance every live DUT's board clock by dt per tick; log a segment log_after_s into a step."""
    t = {d.slot: 100.0 * k for k, d in enumerate(seq.duts)}  # boards have different clocks
    logged = set()
    while not seq.done.is_set():
        for d in seq.duts:
            if not d.live:
                continue
            t[d.slot] += dt
            if d.t0 is None:
                d.t0 = t[d.slot]
            d.last_t = t[d.slot]
            if seq.state == "logging" and not d.at_step_position() and seq.position is not None:
                d.placed_since_t = d.arrived_t = d.last_t  # the board measures the position at once
                d.placed_at = seq.position
            if (
                seq.state == "logging"
                and d.slot not in slow
                and (seq.step_index, d.slot) not in logged
                and d.last_t - d.step_t_start > log_after_s
            ):
                logged.add((seq.step_index, d.slot))
                d.segments.append(_seg(len(d.segments), d.last_t, seq.position))
                d.segment_steps.append(seq.step_index)
        seq.notify()
        await asyncio.sleep(0.001)


def _make(profile, n=3, fixture=True, start_step=0, **limits):
    bus = EventBus()
    q = bus.subscribe(maxsize=100000)
    hw = Hw(bus, MemFixture() if fixture else None, **limits)
    duts = [DutRun(slot=f"s{i}") for i in range(n)]
    seq = Sequencer(7, profile, duts, hw, bus, poll_s=0.01, start_step=start_step)
    hw.seq = seq
    hw.lamp.reset(7)
    return seq, hw, q


def _drain(q):
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


async def test_a_batch_stopped_before_its_task_first_runs_still_ends():
    """Aborted (or shut down) in the same turn of the loop that started it: a task cancelled
    before its first step never runs its body, so the batch never ended and wait_batch hung
    (seen when a retest batch was aborted at once)."""
    seq, hw, q = _make(BUILTIN_PROFILES["fast-thermal"])
    seq.start()
    seq.stop("aborted", "at once", by="Ana")
    await asyncio.wait_for(seq.done.wait(), 5.0)
    assert (seq.state, seq.error, seq.ended_by) == ("aborted", "at once", "Ana")
    assert hw.relay.coil is False


async def test_fast_thermal_with_fixture_runs_every_state_and_ends_lamp_off():
    seq, hw, q = _make(BUILTIN_PROFILES["fast-thermal"])
    seq.start()
    feeder = asyncio.create_task(feed(seq))
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    states = [b for _, _, b in seq.history]
    assert states == [
        "connecting",
        "step_setup", "positioning", "moving", "logging", "step_done",  # P ambient (position unknown)
        "step_setup", "positioning", "logging", "step_done",  # P hot: already at P
        "step_setup", "positioning", "moving", "logging", "step_done",  # N hot: turn the plate
        "step_setup", "positioning", "logging", "step_done",  # N ambient
        "analysing", "finished",
    ]
    assert hw.fixture.moves == [0, 1]
    assert hw.relay.writes == [False, True, True, False, False, False]
    assert hw.relay.coil is False and hw.analysed and hw.released
    assert all(d.state == "done" for d in seq.duts)
    # every DUT logged one segment per step, each annotated with the step's position
    for d in seq.duts:
        assert [s.position for s in d.segments] == [0, 0, 1, 1]
    events = _drain(q)
    assert [e.state for e in events if e.kind == "BatchStateChanged"][-1] == "finished"
    assert [e.step_name for e in events if e.kind == "StepStarted"] == ["P ambient", "P hot", "N hot", "N ambient"]


async def test_step_timeout_in_sample_time_faults_only_late_dut():
    prof = Profile("t", (Step("a", 0, require="segment", timeout_s=500.0), Step("b", 0, require="segment", timeout_s=500.0)))
    seq, hw, q = _make(prof, n=3)
    seq.start()
    feeder = asyncio.create_task(feed(seq, slow={"s1"}))
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    s0, s1, s2 = seq.duts
    assert s1.state == "faulted" and "step 'a' timed out after 50" in s1.fault_reason and "sample time" in s1.fault_reason
    assert s0.state == "done" and s2.state == "done"
    assert len(s0.segments) == 2  # the others went on through step b


async def test_timeout_counts_sample_time_not_wall_time():
    """Slow samples (1 s of board time per tick) keep a 500 s timeout open although wall time flies."""
    prof = Profile("t", (Step("a", 0, require="segment", timeout_s=500.0),))
    seq, hw, q = _make(prof, n=2)
    seq.start()
    feeder = asyncio.create_task(feed(seq, slow={"s0", "s1"}, dt=1.0))
    await asyncio.sleep(0.3)
    assert seq.state == "logging" and all(d.live for d in seq.duts)
    assert seq.clock_s() < 500
    feeder.cancel()
    seq.stop("aborted", "test")
    assert await asyncio.wait_for(seq.task, 5) == "aborted"


async def test_without_fixture_operator_prompt_and_confirmation():
    seq, hw, q = _make(BUILTIN_PROFILES["fast-thermal"], fixture=False)
    seq.start()
    feeder = asyncio.create_task(feed(seq))
    for want in ("P", "N"):
        for _ in range(500):
            if seq.prompt is not None:
                break
            await asyncio.sleep(0.01)
        assert seq.prompt["text"] == f"turn the plate to {want}"
        assert seq.state == "waiting_operator"
        with pytest.raises(ValueError):
            seq.answer_prompt(seq.prompt["id"] + 99)
        seq.answer_prompt(seq.prompt["id"], "done")
        await asyncio.sleep(0.01)
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    prompts = [e for e in _drain(q) if isinstance(e, PromptRaised)]
    assert [p.position for p in prompts] == [0, 1]
    with pytest.raises(ValueError):
        seq.answer_prompt(1)


async def test_abort_switches_lamp_off():
    prof = Profile("t", (Step("hot", 0, lamp=True, require="none", dwell_s=1e6, timeout_s=2e6),))
    seq, hw, q = _make(prof)
    seq.start()
    feeder = asyncio.create_task(feed(seq))
    for _ in range(500):
        if hw.relay.coil:
            break
        await asyncio.sleep(0.01)
    assert hw.relay.coil is True and hw.lamp.is_on
    seq.stop("aborted", "operator")
    assert await asyncio.wait_for(seq.task, 5) == "aborted"
    feeder.cancel()
    assert hw.relay.coil is False and not hw.lamp.is_on
    assert seq.error == "operator"
    assert all(d.state == "interrupted" for d in seq.duts)


async def test_over_temperature_trips_lamp_and_fails_batch():
    prof = Profile("t", (Step("hot", 0, lamp=True, require="none", dwell_s=1e6, timeout_s=2e6),))
    seq, hw, q = _make(prof)
    seq.start()
    feeder = asyncio.create_task(feed(seq))
    for _ in range(500):
        if hw.relay.coil:
            break
        await asyncio.sleep(0.01)
    assert hw.lamp.check_dut_temp("s2", 91.0)
    assert await asyncio.wait_for(seq.task, 5) == "failed"
    feeder.cancel()
    assert hw.relay.coil is False
    assert "s2 at 91.0 C" in seq.error
    with pytest.raises(LampTripped):
        await hw.lamp.set_lamp(True, "again")
    assert any(isinstance(e, Alarm) and "safety trip" in e.text for e in _drain(q))


async def test_all_duts_faulted_fails_batch():
    prof = Profile("t", (Step("a", 0, require="segment", timeout_s=100.0),))
    seq, hw, q = _make(prof, n=2)
    seq.start()
    feeder = asyncio.create_task(feed(seq, slow={"s0", "s1"}))
    assert await asyncio.wait_for(seq.task, 10) == "failed"
    feeder.cancel()
    assert "no DUT left" in seq.error


def test_transition_table_is_closed():
    for src, dsts in TRANSITIONS.items():
        for d in dsts:
            assert d in TRANSITIONS, (src, d)
    seq, hw, q = Sequencer.__new__(Sequencer), None, None
    seq.state, seq.history, seq.batch_id = "created", [], 1
    seq.bus = EventBus()
    with pytest.raises(RuntimeError, match="illegal"):
        seq._transition("logging")


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


async def test_lamp_on_time_follows_samples_and_runs_on_wall_time_when_they_stop():
    bus = EventBus()
    clock = Clock()
    g = LampGuard(MemRelay(), bus, max_on_s=600.0, max_dut_temp_c=85, max_plate_temp_c=90, speed=50.0, clock=clock)
    g.note_sample_time(100.0)
    await g.set_lamp(True, "t")
    # samples flow, late (200 s of samples in 10 wall s at speed 50): what the boards lived through counts
    clock.t += 10.0
    g.note_sample_time(300.0)
    assert g.on_time_s() == pytest.approx(200.0)
    # the stream stops: from the last sample on, wall x speed keeps counting (3 wall s = 150 s)
    clock.t += 3.0
    assert g.on_time_s() == pytest.approx(350.0)
    assert not g.check_on_time()
    clock.t += 5.1  # 200 + (8.1 s x 50) = 605 s > 600 s: a stalled stream cannot keep the lamp on
    assert g.check_on_time()
    await asyncio.sleep(0.05)
    assert g.relay.coil is False and g.trip_reason.startswith("lamp on for 605 s")

    # samples running ahead of wall x speed count in full
    g.reset(2)
    g.note_sample_time(0.0)
    await g.set_lamp(True, "t")
    g.note_sample_time(700.0)
    assert g.on_time_s() == pytest.approx(700.0)


async def test_resumed_batch_lamp_counts_from_its_own_clock_not_from_zero():
    """A batch resumed an hour in: its sample clock starts at 3600 s. A lamp switched on before the
    first new sample arrives counts from there, not from 0 (which tripped a healthy resume at
    'lamp on for 4810 s > max 4800 s' when the daemon was slow to read its boards)."""
    clock = Clock()
    g = LampGuard(MemRelay(), EventBus(), max_on_s=600.0, max_dut_temp_c=85, max_plate_temp_c=90, speed=50.0,
                  clock=clock)
    g.reset(3, sample_now_s=3600.0)
    await g.set_lamp(True, "resumed step")
    clock.t += 1.0
    g.note_sample_time(3650.0)
    assert g.on_time_s() == pytest.approx(50.0)
    assert not g.check_on_time()


async def test_failed_off_write_is_retried_and_alarmed():
    bus = EventBus()
    q = bus.subscribe()
    relay = MemRelay()
    g = LampGuard(relay, bus, max_on_s=1e9, max_dut_temp_c=85, max_plate_temp_c=90, retry_delays_s=(0.001, 0.002, 0.004))
    await g.set_lamp(True, "t")
    relay.fail_next = 2
    assert await g.off("end") is True
    assert relay.coil is False
    alarms = [e for e in _drain(q) if isinstance(e, Alarm)]
    failed = [a for a in alarms if "lamp OFF write failed" in a.text]
    assert len(failed) == 2 and all(a.severity == "critical" for a in failed)
    assert g.state == "off" and [a.text for a in alarms if a not in failed] == ["lamp relay answers again"]
    # a relay that stays dead: off() reports failure, alarms, and keeps retrying in the background
    await g.set_lamp(True, "t")
    relay.fail_next = 6
    assert await g.off("end") is False
    for _ in range(300):
        if relay.coil is False:
            break
        await asyncio.sleep(0.01)
    assert relay.coil is False
    assert any(isinstance(e, LampChanged) and not e.on for e in _drain(q))
    await g.close()


async def test_abort_holds_even_when_a_device_call_swallows_the_cancel():
    """asyncio.wait_for inside a Modbus client can eat the task's cancel (Python 3.11): the
    sequencer must still end 'aborted' at its next turn, lamp off, instead of running on."""
    seq, hw, q = _make(BUILTIN_PROFILES["fast-thermal"])
    entered = asyncio.Event()
    inner = hw.connect_duts

    async def swallowing_connect(s):
        await inner(s)
        entered.set()
        try:
            await asyncio.sleep(0.5)
        except asyncio.CancelledError:
            pass  # what a swallowing wait_for looks like from here

    hw.connect_duts = swallowing_connect
    seq.start()
    await asyncio.wait_for(entered.wait(), 5)
    seq.stop("aborted", "operator pressed abort")
    assert await asyncio.wait_for(seq.task, 5) == "aborted"
    assert seq.error == "operator pressed abort"
    assert not hw.lamp.is_on and hw.released
    assert all(d.state == "interrupted" for d in seq.duts)
    assert "logging" not in [b for _, _, b in seq.history]


async def test_resumed_sequencer_starts_after_the_last_completed_step():
    seq, hw, q = _make(BUILTIN_PROFILES["fast-thermal"], start_step=2)
    seq.start()
    feeder = asyncio.create_task(feed(seq))
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    started = [e.step_index for e in _drain(q) if e.kind == "StepStarted"]
    assert started == [2, 3]
    assert all(d.state == "done" for d in seq.duts)


async def _paced_feed(seq, paces: dict[str, float], clocks: dict[str, float], silent_until_logging=(),
                      log_after_s: float = 300.0) -> None:
    """Each DUT's board clock advances by its own pace per tick (a slow link delivers less sample
    time per tick), one block per tick; a DUT in silent_until_logging sends nothing until the step
    begins logging. Each measures the step's position at once and logs a segment log_after_s after
    it arrives, on its own clock."""
    logged, began = set(), set()
    while not seq.done.is_set():
        for d in seq.duts:
            if d.slot in silent_until_logging and d.slot not in began:
                if seq.state != "logging":
                    continue  # nothing from this link until after Done
                began.add(d.slot)
            clocks[d.slot] += paces[d.slot]
            if d.t0 is None:
                d.t0 = clocks[d.slot]
            d.blocks.append(SampleBlock(np.array([clocks[d.slot]]), np.array([[0.0, 0.0, 1.0]]), np.array([25.0])))
            d.last_t = clocks[d.slot]
            if seq.state == "logging" and not d.at_step_position():
                d.placed_since_t = d.arrived_t = d.last_t
                d.placed_at = seq.position
            if seq.state == "logging" and d.slot not in logged and d.arrived_t is not None \
                    and d.last_t - d.arrived_t > log_after_s:
                logged.add(d.slot)
                d.segments.append(_seg(len(d.segments), d.last_t, seq.position))
                d.segment_steps.append(seq.step_index)
        seq.notify()
        await asyncio.sleep(0.001)


async def test_timeout_runs_on_each_dut_own_clock_not_the_fastest_board():
    """A DUT whose link delivers at a third of the others' pace (a busy CAN adapter) logs its
    segment 300 s into the step on its own clock, when the fastest board is already 900 s in; with
    a 500 s timeout it must not be faulted."""
    prof = Profile("t", (Step("a", 0, require="segment", timeout_s=500.0),))
    seq, hw, q = _make(prof, n=2)
    for d in seq.duts:  # both boards streaming before the step begins
        d.t0 = d.last_t = 0.0
    seq.start()
    feeder = asyncio.create_task(_paced_feed(seq, {"s0": 30.0, "s1": 10.0}, {"s0": 0.0, "s1": 0.0}))
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    assert [d.state for d in seq.duts] == ["done", "done"], [d.fault_reason for d in seq.duts]


async def test_a_link_that_delivers_its_first_sample_after_done_is_timed_on_its_own_clock():
    """A board whose first sample of the batch reaches the station only after the step began
    logging (a link that lags at the batch's start: a loaded host, a busy adapter) had no board
    time to count from and was timed on the fastest board's clock: it arrived, averaged at the
    position and was faulted 'timed out ... without a segment' (a CI run: 2 of 3 healthy DUTs).
    It now counts from its own first sample after Done: its segment, 300 s after it arrives on
    its own clock, ends the step while the fast board's clock is past the 500 s timeout."""
    prof = Profile("t", (Step("a", 0, require="segment", timeout_s=500.0),))
    seq, hw, q = _make(prof, n=2)
    fast, late = seq.duts
    fast.t0 = fast.last_t = 0.0  # streaming before the step begins; `late` has sent nothing yet
    seq.start()
    # the late board's clock is its own (another epoch)
    feeder = asyncio.create_task(_paced_feed(seq, {"s0": 30.0, "s1": 10.0}, {"s0": 0.0, "s1": 5000.0},
                                             silent_until_logging=("s1",)))
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    assert [d.state for d in seq.duts] == ["done", "done"], [d.fault_reason for d in seq.duts]
    assert late.step_clock_start_t() == pytest.approx(5010.0)  # its first sample after Done
    assert fast.last_t - fast.step_t_start > 500.0  # the fast board's clock was past the timeout


async def test_position_is_unknown_while_the_plate_moves():
    """During a fixture move the batch's position is None (samples stored with position -1), not
    the position the plate left; it is the step's once the fixture reports it reached."""
    seq, hw, q = _make(BUILTIN_PROFILES["fast-thermal"])
    seen = []

    class Watching(MemFixture):
        async def position(self):
            seen.append((seq.step_index, seq.state, seq.position, seq.status()["position"]))
            return self.pos

    hw.fixture = Watching()
    seq.start()
    feeder = asyncio.create_task(feed(seq))
    assert await asyncio.wait_for(seq.task, 10) == "finished"
    feeder.cancel()
    # the turn from P (0) to N (1) in step 2: polled while moving, position unknown
    assert (2, "moving", None, None) in seen
    assert all(pos is None for _, state, pos, _ in seen if state == "moving")
    for d in seq.duts:  # segments logged at the reached positions as before
        assert [s.position for s in d.segments] == [0, 0, 1, 1]


async def test_waiting_for_says_what_each_state_and_step_waits_for():
    """The status names what holds the batch (issue 9: a newcomer must see why nothing moves)."""
    verified = BUILTIN_PROFILES["fast-thermal-verified"]
    seq, hw, q = _make(verified)
    assert seq.waiting_for() == "boards"
    heat = next(i for i, s in enumerate(verified.steps) if s.require == "heat")
    prog = next(i for i, s in enumerate(verified.steps) if s.require == "program")
    seq.step_index = 0
    for state, want in [("moving", "fixture"), ("waiting_operator", "operator"), ("logging", "segment"),
                        ("analysing", "analysis"), ("aborted", None)]:
        seq.state = state
        assert seq.waiting_for() == want, state
    seq.state, seq.step_index = "logging", heat
    assert seq.waiting_for() == "temperature rise"
    seq.state, seq.step_index = "programming", prog
    assert seq.waiting_for() == "programming"
    assert seq.status()["note"] is None and seq.status()["analysis"] == "thermal"

    steps = [Step("still", 1, require="static", dwell_s=5.0, timeout_s=100.0),
             Step("wait", 1, require="none", dwell_s=5.0, timeout_s=100.0)]
    seq, hw, q = _make(Profile("w", steps, analysis="none"))
    seq.state, seq.step_index = "logging", 0
    assert seq.waiting_for() == "static dwell"
    seq.step_index = 1
    assert seq.waiting_for() == "dwell"
    # per DUT: a DUT that has what the step needs waits for the others; an ended one for nothing
    d0, d1, d2 = seq.duts
    d0.state = d1.state = "running"
    d0.t0, d0.last_t, d0.step_t_start = 0.0, 10.0, 0.0  # 10 s into a 5 s dwell
    d1.t0, d1.last_t, d1.step_t_start = 0.0, 2.0, 0.0
    for d in (d0, d1):  # both measure the step's position, settled (station/daemon/intake.place)
        d.placed_since_t, d.placed_at, d.step_position = 0.0, 1, 1
    d2.state = "faulted"
    st = seq.status()
    assert [s["waiting_for"] for s in st["slots"]] == ["other DUTs", "dwell", None]
    assert st["waiting_for"] == "dwell" and "no calibration result" in st["note"] and st["analysis"] == "none"
    assert st["counts"] == {"running": 2, "done": 0, "faulted": 1, "interrupted": 0}


async def test_lamp_guard_close_switches_off_even_when_its_watch_swallowed_a_cancel():
    """CI hang (test_decide_e2e, 1 run in 6 on a loaded machine): close() cancelled the watch task
    just as the relay read's asyncio.wait_for completed (Python 3.11 then returns the result and
    the cancel is gone); the watch ran on, `await task` never returned, and the lamp OFF after it
    was never sent. Here the watch swallows the first cancel the same way."""

    class Guard(LampGuard):
        async def _watch(self) -> None:
            swallowed = False
            while True:
                try:
                    await asyncio.sleep(0.01)
                except asyncio.CancelledError:
                    if swallowed:
                        raise
                    swallowed = True  # as wait_for does when its inner wait completes with the cancel

    relay = MemRelay()
    g = Guard(relay, EventBus(), max_on_s=1e9, max_dut_temp_c=85, max_plate_temp_c=90)
    await g.set_lamp(True, "t")
    g.start()
    await asyncio.sleep(0.03)
    closing = asyncio.create_task(g.close())
    await asyncio.wait({closing}, timeout=5.0)  # not wait_for: its own cancel would unblock the old close
    hung = not closing.done()
    if hung:
        g._watch_task = None
        closing.cancel()
    assert not hung, "LampGuard.close() hangs on a watch task that swallowed a cancel"
    assert closing.result() is True
    assert relay.coil is False and g.state == "off"
