"""A replayed step begins at the sample its recorded step began at (station/replay/director.py).

The recorded start of each step (the batch's step windows) becomes a hold on the replayed record,
kept until the replaying daemon has begun that step. Truth: indices into the record, computed
here from its sample times.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from contracts.recording import RecordedDut, Recording
from contracts.types import Identity
from drivers.sim.replay import ReplayWorld
from station.replay.director import Director

ODR_HZ = 3.125


def _dut(n: int = 2000, starts: dict[int, float] | None = None) -> RecordedDut:
    t = np.arange(n) / ODR_HZ
    return RecordedDut(slot="s01", serial="SIM0001", link="serial", identity=Identity("SIM0001", odr_hz=ODR_HZ),
                       time_s=t, acc_counts=np.zeros((n, 3), dtype=np.int64),
                       temp_counts=np.full(n, 25, dtype=np.int64), step_start_t=dict(starts or {}))


def test_step_start_index_is_the_sample_after_the_recorded_start_and_outside_starts_are_left_out():
    d = _dut(starts={0: -1.0, 1: 100.0, 2: 200.16, 3: 1e6})
    # 100.0 s is sample 312.5 -> the first sample after it is 313; 200.16 s lies on sample 625.5 -> 626
    assert d.step_start_indices() == [(1, 313), (2, 626)]


def test_a_step_hold_stops_the_record_there_and_a_prompt_hold_replaces_it():
    w = ReplayWorld([_dut()])
    w.start_dut(0)
    w.hold_at_step_start(0, 313)
    w.advance(1000)
    assert w.next_index(0) == 313  # samples 0..312 sent, the record waits
    w.advance(1000)
    assert w.next_index(0) == 313
    w.hold(0, 400)  # a prompt answered further on: the step hold gives way
    w.advance(1000)
    assert w.next_index(0) == 400
    w.release()
    w.advance(5000)
    assert w.done(0)


def test_director_holds_until_the_daemon_begins_the_step_then_lets_go():
    d = _dut(starts={1: 100.0, 2: 200.16})
    w = ReplayWorld([d])
    w.start_dut(0)
    station = SimpleNamespace(begun=0)
    station.step_begun = lambda batch_id: station.begun
    director = Director(Recording("test", "fast-thermal", [d]), station, SimpleNamespace(world=w, ordered=[d]), 1)
    waits: dict = {}

    director._hold_at_step_starts(w, waits)
    w.advance(1000)
    assert w.next_index(0) == 313  # held after the recorded start of step 1: the daemon is still in step 0
    director._hold_at_step_starts(w, waits)
    w.advance(1000)
    assert w.next_index(0) == 313

    station.begun = 1  # the daemon began step 1: the record goes on, to the start of step 2
    director._hold_at_step_starts(w, waits)
    w.advance(1000)
    assert w.next_index(0) == 626

    station.begun = None  # the batch ended: no hold
    director._hold_at_step_starts(w, waits)
    w.advance(5000)
    assert w.done(0) and not director.notes
