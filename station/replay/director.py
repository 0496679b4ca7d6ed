"""The recorded line's hands in a replay: the operator's answers, the program stops, the end.

A recorded batch is more than its samples: an operator confirmed "turn the plate to N" at some
moment, the station stopped each board to program it, and the batch ended (finished, aborted,
failed) where the recording ends. The replaying daemon must meet each of these at the same point
of the recorded streams, or it sees other samples in another state than the line did (a prompt
answered late leaves samples at an unknown position; a board programmed at another point gets raw
samples judged as compensated). The director watches the replaying daemon and the replayed plant
(drivers/sim/replay.py ReplayWorld) and acts only through what a line has: the prompt's answer,
the operator's abort, and the boards' streams.

- A prompt "turn the plate to P" is answered where the recorded operator's answer took effect:
  each DUT's record is held at its first sample the station stored at P after the current point
  (contracts/recording.py answer_index); once every DUT is there and the daemon has taken in every sample sent,
  the prompt is answered and the records go on. A prompt the recording never answered (the
  recorded batch was aborted there, or the recording ends) stays open: the recording runs out.
- A DUT whose record waits at its recorded program stop is held there for as long as the replaying
  daemon will still stop its board (Station.stop_pending: its program step is ahead or running,
  however long the analysis before the writes takes on a loaded machine). It is let go, with a
  note, HOLD_TIMEOUT_S after the daemon no longer will (another profile or config replayed, the
  DUT faulted), or after STOP_WAIT_MAX_S in any case.
- Each DUT's record is held just after the sample at which the recorded station began each step
  (the batch's step windows) until the replaying daemon has begun that step too: a step then
  counts its dwell or its heat from the same sample, however long the analysis, the writes or a
  retried write before it took on this machine.
- When the recording is over and the recorded batch did not finish, the replay ends there too:
  the batch is aborted "where the recording ends", which the comparison reads as unchanged
  (runner.py), instead of a stalled daemon faulting slots or a lamp timer running on.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field
from typing import Any

from contracts.recording import Recording, answer_index

log = logging.getLogger(__name__)

POLL_S = 0.02
PASS_MAX_S = 1.0  # wall seconds between passes over the DUTs while nothing moves (their timeouts are seconds)
HOLD_TIMEOUT_S = 5.0  # wall seconds a hold may wait for what the daemon should do there
STOP_WAIT_MAX_S = 300.0  # wall seconds a record waits at its program stop for a daemon still on its way there
STEP_HOLD_MAX_S = 120.0  # wall seconds a record waits at a recorded step start for the daemon to begin that step
RECORDING_END = "the recording ends here"


@dataclass
class Director:
    recording: Recording
    station: Any  # station.daemon.supervisor.Station
    sim: Any  # drivers.sim.replay.ReplayStation
    batch_id: int
    notes: list[str] = field(default_factory=list)
    ended_at_recording_end: bool = False
    _answered: set[int] = field(default_factory=set)
    _step_starts: dict[int, list[tuple[int, int]]] = field(default_factory=dict)  # DUT -> its (step, index)

    # ---- the loop -------------------------------------------------------------------------
    async def run(self) -> None:
        """Until cancelled (the runner cancels it when the batch has ended). A pass over every DUT
        is made when what the holds read has changed (the step the daemon has begun, a record's
        next index: ReplayWorld.moves), while a DUT waits at its program stop, and at least every
        PASS_MAX_S otherwise: a poll in which nothing moved costs no work per DUT (the world
        advances once a clock tick, less often than the director polls, and not at all while it
        waits for the daemon)."""
        world = self.sim.world
        stop_waits: dict[int, list[float]] = {}
        step_waits: dict[int, tuple[int, int, float]] = {}
        seen: tuple[int | None, int] | None = None
        t_pass = 0.0
        while True:
            await asyncio.sleep(POLL_S)
            try:
                prompt = self.station.prompt(self.batch_id)
            except KeyError:
                return
            if prompt is not None and prompt["id"] not in self._answered:
                await self._answer(prompt)
                seen = None
                continue
            now = time.monotonic()
            state = (self._begun(), int(world.moves))
            if state == seen and not stop_waits and now - t_pass < PASS_MAX_S:
                continue
            seen, t_pass = state, now
            self._let_go_of_stops(world, stop_waits)
            self._hold_at_step_starts(world, step_waits)
            if not self.ended_at_recording_end and self._recording_over(world):
                await self._end_at_recording_end()

    def _begun(self) -> int | None:
        """The step the daemon has begun (Station.step_begun); None once the batch is gone."""
        try:
            begun: int | None = self.station.step_begun(self.batch_id)
        except KeyError:
            return None
        return begun

    # ---- prompts ----------------------------------------------------------------------------
    async def _answer(self, prompt: dict) -> None:
        world = self.sim.world
        self._answered.add(prompt["id"])
        wanted = prompt.get("position")
        holds = {}
        for i, d in enumerate(self.sim.ordered):
            # a record not started yet (the first prompt can come before every board streams) is
            # held from its beginning: its next index is 0
            if wanted is None or world.done(i):
                continue
            k = answer_index(d.position, world.next_index(i), int(wanted))
            if k is not None:
                holds[i] = k
        if wanted is not None and not holds:
            self.notes.append(f"prompt '{prompt['text']}' left open: the recording never reaches position "
                              f"{prompt.get('position_name')} after it")
            return
        for i, k in holds.items():
            world.hold(i, k)
        # wait while the streams still move towards the answer (a loaded machine is slow, not
        # stuck); answer anyway once nothing moved for HOLD_TIMEOUT_S
        t0, moved = time.monotonic(), None
        while not all(world.at_hold(i) for i in holds) or not self._taken_all():
            now_moved = (tuple(world.next_index(i) for i in holds), self._taken())
            if now_moved != moved:
                t0, moved = time.monotonic(), now_moved
            if time.monotonic() - t0 > HOLD_TIMEOUT_S:
                self.notes.append(f"prompt '{prompt['text']}': not every DUT reached the recorded answer, and "
                                  f"nothing moved for {HOLD_TIMEOUT_S:g} s; answered anyway")
                break
            await asyncio.sleep(POLL_S)
        try:
            self.station.answer_prompt(self.batch_id, prompt["id"], "done", by="replay (as recorded)")
        except (ValueError, KeyError):  # the batch ended or moved on meanwhile
            world.release()
            return
        t0 = time.monotonic()
        while time.monotonic() - t0 < HOLD_TIMEOUT_S:  # the sequencer takes the answer (position set)
            try:
                now = self.station.prompt(self.batch_id)
            except KeyError:
                break
            if now is None or now["id"] != prompt["id"]:
                break
            await asyncio.sleep(POLL_S / 4)
        world.release()
        ref = next(iter(holds), None)
        if ref is not None:
            d = self.sim.ordered[ref]
            self.notes.append(f"prompt '{prompt['text']}' answered at the recorded answer "
                              f"({d.slot}: sample {holds[ref]}, t = {float(d.time_s[holds[ref]]):.1f} s)")

    def _taken(self) -> tuple:
        try:
            return tuple(sorted(self.station.samples_taken(self.batch_id).items()))
        except KeyError:
            return ()

    def _taken_all(self) -> bool:
        """The daemon has taken in every sample the replay boards have sent (live DUTs)."""
        try:
            taken = self.station.samples_taken(self.batch_id)
        except KeyError:
            return True
        world = self.sim.world
        return all(taken.get(d.slot, world.sent[i]) >= world.sent[i] for i, d in enumerate(self.sim.ordered))

    # ---- program stops ------------------------------------------------------------------------
    def _let_go_of_stops(self, world: Any, waits: dict[int, list[float]]) -> None:
        """waits[i] = [when DUT i began waiting at its stop, when the wait was last justified]."""
        now = time.monotonic()
        for i, d in enumerate(self.sim.ordered):
            if not world.waiting_for_stop(i):
                waits.pop(i, None)
                continue
            w = waits.setdefault(i, [now, now])
            try:
                pending = self.station.stop_pending(self.batch_id, d.slot)
            except KeyError:
                pending = False
            if pending and now - w[0] <= STOP_WAIT_MAX_S:
                w[1] = now
            if now - w[1] > HOLD_TIMEOUT_S:
                world.drop_stop(i)
                waits.pop(i, None)
                self.notes.append(f"{d.slot}: the replaying daemon did not stop the board where the recorded "
                                  f"one was stopped for programming (t = {d.restart_after_t:.1f} s): let go")

    # ---- step starts ----------------------------------------------------------------------------
    def _hold_at_step_starts(self, world: Any, waits: dict[int, tuple[int, int, float]]) -> None:
        """Hold each DUT's record just after its recorded start of the next step the daemon has not
        begun, so that the step begins at the same sample as on the line. (A heat step counts its
        rise from there: begun a few hundred recorded seconds late, behind boards that streamed on
        while another board's write was retried, its rise never came within the recording and the
        lamp timer ran on to a trip.) waits[i] = (step, index, when the hold was set); a hold the
        daemon does not reach within STEP_HOLD_MAX_S (another profile or config replayed, the
        DUT faulted, a step ended otherwise) is let go with a note."""
        try:
            begun = self.station.step_begun(self.batch_id)
        except KeyError:
            begun = None
        now = time.monotonic()
        for i, d in enumerate(self.sim.ordered):
            if begun is None or world.done(i):
                if i in waits:
                    world.hold_at_step_start(i, None)
                    waits.pop(i)
                continue
            nxt = world.next_index(i)
            if i not in self._step_starts:  # once per DUT: the record does not change
                self._step_starts[i] = d.step_start_indices()
            due = next(((k, idx) for k, idx in self._step_starts[i] if k > begun and idx >= nxt), None)
            held = waits.get(i)
            if due is None:
                if held is not None:
                    world.hold_at_step_start(i, None)
                    waits.pop(i)
                continue
            if held is not None and held[:2] == due:
                if now - held[2] > STEP_HOLD_MAX_S and held[2] >= 0:
                    world.hold_at_step_start(i, None)
                    waits[i] = (*due, -1.0)  # let go for good
                    self.notes.append(f"{d.slot}: the replaying daemon did not begin step {due[0]} where the "
                                      f"recorded one did (t = {d.step_start_t[due[0]]:.1f} s): let go")
                continue
            world.hold_at_step_start(i, due[1])
            waits[i] = (*due, now)

    # ---- the end ------------------------------------------------------------------------------
    def _recording_over(self, world: Any) -> bool:
        return self.recording.batch_state != "finished" and world.exhausted

    async def _end_at_recording_end(self) -> None:
        t0 = time.monotonic()
        while not self._taken_all() and time.monotonic() - t0 < HOLD_TIMEOUT_S:
            await asyncio.sleep(POLL_S)
        rec = self.recording
        why = f"{RECORDING_END} (the recorded batch {rec.batch_state}: {rec.batch_error or '-'})"
        try:
            self.station.abort(self.batch_id, why, by="replay")
        except (ValueError, KeyError):
            return  # it ended on its own meanwhile
        self.ended_at_recording_end = True
        self.notes.append(why)
