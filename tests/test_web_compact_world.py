"""A 64-DUT batch late in a long run, for tests/test_web_compact.py and tests/test_browser_compact.py
(no tests here): what the operator page polls must stay small however big the batch's status gets.

Running 64 simulated boards through a 72-step batch would take the machine for an hour, so the big
batch is made from a real one: a small station (tests/web_support.LiveStation: simulated boards,
the daemon, SQLite, the web app) runs fast-thermal-verified to its end, which gives real DUT runs
(samples, segments, the thermal result, program and verify, the verdict). Those runs are copied
into 64 slots (each its own serial and label; the copies keep their source's stored run, so the
page's plot and result fetches find one) of a real Sequencer on the sfem-24 profile (72 steps),
set late in the batch (step 61 of 72) with thousands of transitions behind it and a prompt asked
again, and registered with the daemon as a batch it holds. The station's own status code then
builds its status (station/daemon/batch_view.py status, progress.py batch_extras) and the real
routes serve it: nothing of the web side is stubbed.

`running`: 40 slots logging, 12 finished with their full result, program-and-verify record and
verdict, 12 faulted with a long reason and an error verdict. `ended`: the same batch finished,
every slot done with its result and verdict.
"""

from __future__ import annotations

import dataclasses
import time

import httpx

from contracts.events import EventBus
from contracts.trace import Trace
from station.daemon.dut_run import DutRun
from station.daemon.sequencer import Sequencer
from station.profiles import BUILTIN_PROFILES
from web_support import LiveStation, auth, wait_for

N_SLOTS = 64
STEP_NOW = 60  # index of the running step: late in sfem-24's 72 steps
TRANSITIONS_PER_STEP = 40  # a long batch: each step set up, moved, asked again, logged ...
FAULT = ("serial /dev/ttyUSB{i}: link lost: [Errno 5] Input/output error (no frame for 12.0 s during step "
         "'+x+y @ 65 C'; the board stopped answering: check its cable and the USB hub)")
TRACE = Trace(work_order="WO-24-0815", part_number="ACC-3DSH-01", part_revision="C", lot="L2411-07")


def finished_batch(live: LiveStation, timeout_s: float = 240.0) -> int:
    """Run fast-thermal-verified on every slot of the small station to its end (the fixture turns
    the plate); every DUT done with its verdict. Its id."""
    with httpx.Client(base_url=live.url, timeout=30, headers=auth("operator")) as c:
        r = c.post("/api/batches", json={"profile": "fast-thermal-verified", "operator": "Ana"})
        assert r.status_code == 201, r.text
        bid = r.json()["id"]
        wait_for(lambda: c.get(f"/api/batches/{bid}").json()["state"] in ("finished", "aborted", "failed"), timeout_s,
                 interval_s=0.5, what=f"batch {bid} ended")
    seq = live.station.batches[bid]
    assert seq.state == "finished", seq.error
    assert all(d.state == "done" and d.result is not None and d.verdict for d in seq.duts), \
        [(d.slot, d.state, d.fault_reason) for d in seq.duts]
    return bid


def _slot_name(i: int) -> str:
    return f"s{i + 1:02d}" if i < 48 else f"c{i - 47:02d}"


def _copy(src: DutRun, i: int, kind: str) -> DutRun:
    """Slot i as a copy of a real run: 'done' (its result, program, verification and verdict),
    'running' (logging, nothing decided yet) or 'faulted' (a lost link, an error verdict)."""
    serial = f"{src.serial}-{i + 1:03d}"
    assert src.identity is not None and src.verdict is not None
    d = dataclasses.replace(src, slot=_slot_name(i), identity=dataclasses.replace(src.identity, serial=serial),
                            label_serial=serial, n_samples=1_234_567 + 7919 * i, steps_done=STEP_NOW,
                            link_stats=dict(src.link_stats), step_windows=dict(src.step_windows))
    d.segments = list(src.segments) * 3
    if kind == "running":
        d.state, d.result, d.verdict, d.program, d.verification = "running", None, None, None, None
    elif kind == "faulted":
        d.state, d.result, d.program, d.verification = "faulted", None, None, None
        d.fault_reason = FAULT.format(i=i)
        d.verdict = {**src.verdict, "verdict": "error", "grade": None, "tray": "rework (error)",
                     "reason": f"faulted: {d.fault_reason}", "reasons": [d.fault_reason]}
    else:
        d.verdict = {**src.verdict, "reason": "all limits met (" + ", ".join(f"{a} TDSF within +-500 ppm/C"
                                                                             for a in "xyz") + ")"}
    return d


def _history(started: float, steps: int) -> list[tuple[float, str, str]]:
    """The sequencer's transitions of `steps` completed steps and the running one (step_rows reads
    the step boundaries from them): each step set up, moved, a person asked again and again."""
    out: list[tuple[float, str, str]] = [(started, "created", "connecting")]
    t, state = started + 5.0, "connecting"
    for k in range(steps + 1):
        chain = ["step_setup", "positioning", "moving"]
        chain += ["waiting_operator", "logging"] * ((TRANSITIONS_PER_STEP - 5) // 2)
        chain += ["logging"] if chain[-1] != "logging" else []
        if k < steps:
            chain.append("step_done")
        for new in chain:
            out.append((t, state, new))
            state, t = new, t + 7.0
    return out


def big_batch(live: LiveStation, src_bid: int, new_bid: int, *, ended: bool) -> int:
    """Register a 64-slot copy of batch src_bid (see the module doc) with the daemon as batch
    new_bid; its id. `ended`: finished, every slot done; else running late in the batch."""
    src = live.station.batches[src_bid]

    def make() -> int:
        kinds = ["done"] * N_SLOTS if ended else ["running"] * 40 + ["done"] * 12 + ["faulted"] * 12
        duts = [_copy(src.duts[i % len(src.duts)], i, kinds[i]) for i in range(N_SLOTS)]
        profile = BUILTIN_PROFILES["sfem-24"]
        trace = dataclasses.replace(TRACE, labels={d.slot: d.label_serial or "" for d in duts})
        seq = Sequencer(new_bid, profile, duts, src.hw, EventBus(), operator="Ana", trace=trace)
        started = time.time() - 6 * 3600
        seq.started_wall = started
        seq.history = _history(started, STEP_NOW)
        seq.step_index = STEP_NOW
        seq.step_clock_start = max(0.0, seq.clock_s() - 30.0)
        if ended:
            seq.step_index = len(profile.steps) - 1
            seq.history = _history(started, len(profile.steps))
            seq.history += [(time.time() - 60, "step_done", "analysing"), (time.time() - 50, "analysing", "finished")]
            seq.state, seq.ended_wall, seq.ended_by = "finished", time.time() - 50, "station"
        else:
            seq.state = "logging"
            step = profile.steps[STEP_NOW]
            reason = ", ".join(d.slot for d in duts[:40]) + f" face +y, not {step.position_name} (a wrong turn?)"
            seq.plate.prompt = {"id": 4711, "kind": "turn_plate", "text": f"{reason}: turn the plate to "
                                f"{step.position_name}", "position": step.position, "position_name": step.position_name,
                                "step_index": STEP_NOW, "again": True, "reason": reason,
                                "direction": [0.707107, -0.707107, 0.0]}
        live.station.batches[new_bid] = seq
        return new_bid

    return live.call(make)


def forget(live: LiveStation, bid: int) -> None:
    """Take the copied batch off the daemon again (a running one would refuse new batches)."""
    live.call(lambda: live.station.batches.pop(bid, None))
