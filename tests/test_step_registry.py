"""A step kind is one registered object (station/steps): a kind defined here, in the test, runs
through a Sequencer, the status, the time estimate and a site config with no other file touched;
an unknown kind is a clear error when the profile is loaded, never a KeyError while a batch runs.

The hardware is played as in tests/test_sequencer.py: an in-memory lamp relay and fixture, and a
feeder that advances each DUT's board clock and places it at the step's position at once.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator, Sequence
from types import SimpleNamespace

import pytest

from contracts.events import EventBus
from contracts.types import StationError
from drivers.base import Chamber, Fixture, LampRelay
from station.config import parse_config
from station.daemon import progress
from station.daemon.dut_run import DutRun
from station.daemon.safety import LampGuard
from station.daemon.sequencer import Sequencer
from station.profiles import Profile, all_profiles
from station.steps import Step, StepKind, kind_names, register, unregister


class Soak(StepKind):
    """The lamp off; every DUT logs `dwell_s` sample seconds at the position (a soak)."""

    name = "soak"
    summary = "the lamp off, dwell_s sample seconds at the position"
    waits_for = "soak"

    def check(self, steps: Sequence[Step], i: int, analysis: str) -> None:
        if steps[i].lamp:
            raise ValueError(f"steps[{i}]: a soak keeps the lamp off")
        if steps[i].dwell_s <= 0:
            raise ValueError(f"steps[{i}]: a soak needs dwell_s > 0")

    def done(self, d: DutRun, step: Step, index: int) -> bool:
        w = d.requirement_window()  # samples placed at the step's position, from when they count
        return w is not None and w[1] - w[0] >= step.dwell_s

    def need_words(self, step: Step) -> str:
        return f"{step.dwell_s:g} s of soak"


@pytest.fixture
def soak() -> Iterator[Soak]:
    kind = register(Soak())
    yield kind
    unregister("soak")


# ---------------------------------------------------------------- fake hardware (as test_sequencer)
class MemRelay(LampRelay):
    def __init__(self) -> None:
        self.coil: bool | None = None
        self.writes: list[bool] = []

    async def set_lamp(self, on: bool) -> None:
        self.coil = on
        self.writes.append(on)

    async def read_lamp(self) -> bool:
        return bool(self.coil)


class MemFixture(Fixture):
    def __init__(self) -> None:
        self.pos = 0

    async def move_to(self, position: int) -> None:
        self.pos = position

    async def position(self) -> int:
        return self.pos

    async def moving(self) -> bool:
        return False


class Hw:
    def __init__(self, bus: EventBus) -> None:
        self.relay = MemRelay()
        self.lamp = LampGuard(self.relay, bus, retry_delays_s=(0.001,), max_on_s=1e9, max_dut_temp_c=85.0,
                              max_plate_temp_c=90.0)
        self.fixture: Fixture | None = MemFixture()
        self.chamber: Chamber | None = None
        self.fixture_timeout_s = 1.0
        self.plate_again_after_s = 1e9
        self.speed = 1.0

    async def connect_duts(self, seq: Sequencer) -> None:
        for d in seq.duts:
            d.state = "running"

    async def release_duts(self, seq: Sequencer) -> None:
        for d in seq.duts:
            if d.live:
                d.state = "done" if seq.ending == "finished" else "interrupted"

    def fault_dut(self, seq: Sequencer, d: DutRun, reason: str) -> None:
        d.state, d.fault_reason = "faulted", reason
        seq.notify()

    async def analyse(self, seq: Sequencer) -> None:
        pass

    async def program_duts(self, seq: Sequencer) -> None:
        pass


async def feed(seq: Sequencer, bumped: Sequence[str] = (), dt: float = 10.0) -> None:
    """Advance every live DUT's board clock by dt per tick; it measures the step's position at once.
    A `bumped` DUT is knocked every tick: its run of placed samples starts over each time."""
    t = {d.slot: 100.0 * k for k, d in enumerate(seq.duts)}
    while not seq.done.is_set():
        for d in seq.duts:
            if not d.live:
                continue
            t[d.slot] += dt
            d.t0 = t[d.slot] if d.t0 is None else d.t0
            d.last_t = t[d.slot]
            if seq.state == "logging" and seq.position is not None:
                if not d.at_step_position():
                    d.placed_since_t = d.arrived_t = d.last_t
                    d.placed_at = seq.position
                elif d.slot in bumped:
                    d.placed_since_t = d.last_t
        seq.notify()
        await asyncio.sleep(0.001)


def _make(profile: Profile, n: int = 3) -> tuple[Sequencer, Hw]:
    bus = EventBus()
    hw = Hw(bus)
    seq = Sequencer(7, profile, [DutRun(slot=f"s{i}") for i in range(n)], hw, bus, poll_s=0.01)
    hw.lamp.reset(7)
    return seq, hw


STATION = SimpleNamespace(config=SimpleNamespace(timing=SimpleNamespace(speed=1.0)))


# ---------------------------------------------------------------- the tests
async def test_a_kind_registered_in_the_test_runs_through_the_sequencer(soak: Soak) -> None:
    prof = Profile("soak-then-heat-soak", (
        Step("soak P", 0, require="soak", dwell_s=200.0, timeout_s=2000.0),
        Step("hot", 0, lamp=True, require="none", dwell_s=50.0, timeout_s=500.0),
        Step("soak N", 1, require="soak", dwell_s=100.0, timeout_s=2000.0),
    ))
    seq, hw = _make(prof)
    task = seq.start()
    feeder = asyncio.create_task(feed(seq))
    seen: list[tuple[str, str, list[str], str, bool, bool | None]] = []
    while not seq.done.is_set():
        if seq.state == "logging" and seq.step_index == 0:
            st = seq.status()
            extras = progress.batch_extras(STATION, seq)
            seen.append((st["waiting_for"], st["step"]["require"], [s["waiting_for"] for s in st["slots"]],
                         extras["steps"][0]["kind"], "error" not in extras["time_left"], hw.relay.coil))
        await asyncio.sleep(0.002)
    assert await asyncio.wait_for(task, 10) == "finished"
    feeder.cancel()
    assert all(d.state == "done" and d.steps_done == 3 for d in seq.duts)
    # the page names what the soak waits for by the kind's own words, the step list and the estimate work
    assert seen and all(w == "soak" and req == "soak" and kind == "step" and ok and coil is False
                        for w, req, slots, kind, ok, coil in seen)
    assert all(set(slots) <= {"soak", "other DUTs"} for _, _, slots, *_ in seen)
    assert hw.relay.writes == [False, True, False, False, False]  # per step, then off for the analysis and the end
    for d in seq.duts:  # each soak ended once the DUT had its 200 s / 100 s of samples at the position
        a, b = d.step_windows[0]
        assert 200.0 <= b - a < 250.0
        a, b = d.step_windows[2]
        assert 100.0 <= b - a < 150.0
    # the estimate asks the kind too: the base class's dwell estimate, capped by the timeout
    assert progress.expected_s(seq)[0] == (200.0, 0.0)


async def test_a_registered_kind_s_timeout_says_what_the_dut_lacked(soak: Soak) -> None:
    prof = Profile("t", (Step("soak", 0, require="soak", dwell_s=100.0, timeout_s=400.0),))
    seq, hw = _make(prof, n=2)
    task = seq.start()
    feeder = asyncio.create_task(feed(seq, bumped=("s1",)))
    assert await asyncio.wait_for(task, 10) == "finished"
    feeder.cancel()
    s0, s1 = seq.duts
    assert s0.state == "done"
    assert s1.state == "faulted" and "step 'soak' timed out after 400 s sample time without 100 s of soak" \
        in s1.fault_reason


def test_the_kind_s_own_rules_are_checked_when_the_profile_is_made(soak: Soak) -> None:
    with pytest.raises(ValueError, match=r"steps\[0\]: a soak keeps the lamp off"):
        Profile("t", (Step("soak", 0, lamp=True, require="soak", dwell_s=10.0),))
    with pytest.raises(ValueError, match="is registered already"):
        register(Soak())


def test_a_site_profile_names_a_registered_kind(soak: Soak) -> None:
    cfg = parse_config(_site({"name": "soak", "position": "N", "require": "soak", "dwell_s": 60, "timeout_s": 600}))
    step = all_profiles(cfg)["site"].steps[0]
    assert step.kind is soak and step.to_json()["require"] == "soak"
    with pytest.raises(StationError, match=r"profiles\.site: steps\[0\]: a soak needs dwell_s > 0"):
        parse_config(_site({"name": "soak", "position": "N", "require": "soak", "timeout_s": 600}))


def test_an_unknown_kind_is_a_config_error_at_load_not_a_key_error_at_run_time() -> None:
    assert "soak" not in kind_names()  # the fixture above unregistered it
    with pytest.raises(StationError) as err:
        parse_config(_site({"name": "a", "position": "P", "require": "soak", "dwell_s": 60, "timeout_s": 600}))
    assert str(err.value) == ("config <dict>: profiles.site.steps[0].require: unknown step kind 'soak' "
                              "(known: segment, static, none)")
    # a kind the station adds itself (program and verify) is not named in a site profile's steps
    with pytest.raises(StationError, match="step kind 'program' cannot be named in a profile's steps"):
        parse_config(_site({"name": "a", "position": "P", "require": "program", "timeout_s": 600}))
    # a profile made in code: a ValueError naming the step when it is made, not when the batch runs
    with pytest.raises(ValueError, match=r"steps\[1\]\.require must be one of \('segment', .*\), not 'soak'"):
        Profile("t", (Step("a", 0, require="none", dwell_s=1.0), Step("b", 0, require="soak", dwell_s=1.0)))
    with pytest.raises(ValueError, match="unknown step kind 'soak'"):
        _ = Step("b", 0, require="soak").kind


def _site(step: dict[str, object]) -> dict[str, object]:
    return {"slots": [{"name": "s01", "serial": "/dev/ttyACM0"}],
            "lamp": {"tcp": {"host": "127.0.0.1", "port": 5020}, "unit": 1},
            "profiles": {"site": {"analysis": "none", "steps": [step]}}}
