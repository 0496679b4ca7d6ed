"""The run's end: analysis, program-and-verify, each DUT's end state, then the verdict's moment.

`RunEnd` is what the sequencer's batch reaches at its end (station/daemon/rig.py hands it the
calls), built from the slot bank, the storage and the verdict's context, each through a narrow
Protocol below; it calls nothing above it:
- `analyse`: the calibration result of every live DUT with data (thermal or SFEM, two at a time
  in worker threads so the pumps of other batches keep their core), published WITHOUT a verdict;
  after a programming step, the verification instead (station/daemon/program_verify.py);
- `program_duts`: the program step: the first pass's analysis, then program_verify writes it;
- `release_duts`: the pumps stop, the boards stop, everything stored so far must be committed, and
  each live DUT gets its end state (done; interrupted with the batch's reason; faulted when its data
  were not stored); a slot whose DUT faulted but whose board still answers is ready again
  (`identified`) for the next batch. Only then is every run judged, once, from that final state
  (station/decisions/moment.judge_final): no fault, abort or failed verification can come after a
  verdict and leave a pass behind (design 8).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Protocol

from contracts.events import DutResult
from contracts.types import StationError
from station.daemon import program_verify
from station.daemon.dut_run import DutRun
from station.daemon.identity_check import board_restart
from station.daemon.program_verify import ProgramHost
from station.daemon.results import sfem_result, thermal_result
from station.daemon.sequencer import Sequencer
from station.decisions import moment
from station.decisions.verdict_context import VerdictContext

ANALYSIS_THREADS = 2  # two cores: do not starve the pumps of other work


class EndSlots(ProgramHost, Protocol):
    """What the run's end needs of the slots (slots.SlotBank is one), beyond program and verify's."""

    async def stop_streams(self, seq: Sequencer) -> None: ...

    async def stop_board(self, d: DutRun) -> bool: ...

    async def slot_free(self, d: DutRun, answered: bool, shutting_down: bool) -> None: ...

    def publish_dut(self, seq: Sequencer, d: DutRun) -> None: ...


class EndStorage(Protocol):
    """The storage's one question at a run's end (storage.Storage is one)."""

    async def stored_before_end(self, timeout_s: float = 15.0) -> str | None: ...


class RunEnd:
    """Analysis, program and verify, end states and the verdict's moment of a batch (module doc)."""

    def __init__(self, slots: EndSlots, storage: EndStorage, verdicts: VerdictContext, *,
                 analyse_results: bool = True, shutting_down: Callable[[], bool] = lambda: False) -> None:
        self.slots = slots
        self.storage = storage
        self.verdicts = verdicts
        self.analyse_results = analyse_results
        self.shutting_down = shutting_down

    async def analyse(self, seq: Sequencer) -> None:
        if program_verify.after_programming(seq):  # the first pass was analysed in the program step
            await program_verify.verify_duts(self.slots, seq)
            return
        await self._analyse(seq)

    async def program_duts(self, seq: Sequencer) -> None:
        await self._analyse(seq)  # the first pass's TDB/TDSF (faults the DUTs whose analysis fails)
        await program_verify.program_duts(self.slots, seq)

    async def _analyse(self, seq: Sequencer) -> None:
        if not self.analyse_results:
            return
        kind = seq.profile.analysis
        duts = [d for d in seq.duts if d.live and d.n_samples > 0]
        if kind == "none" or not duts:
            return
        sem = asyncio.Semaphore(ANALYSIS_THREADS)
        bus = self.slots.bus

        async def one(d: DutRun) -> None:
            async with sem:
                try:
                    if kind == "thermal":
                        full_range_c = moment.operating_range_c(self.verdicts, d.identity, seq.trace.part_number)
                        thermal = await asyncio.to_thread(thermal_result, d, full_range_c)
                        d.result = thermal
                        bus.publish(DutResult(seq.batch_id, slot=d.slot, serial=d.serial or "", thermal=thermal))
                    elif kind == "sfem":
                        sfem = await asyncio.to_thread(sfem_result, d, seq.profile)
                        d.result = sfem
                        bus.publish(DutResult(seq.batch_id, slot=d.slot, serial=d.serial or "", sfem=sfem))
                except StationError as exc:  # InsufficientData and friends: this DUT only
                    self.slots.fault_dut(seq, d, f"analysis: {exc}")

        await asyncio.gather(*(one(d) for d in duts))

    def _restarted(self, d: DutRun) -> str | None:
        """The same board, restarted during its run (its `boots` moved between the identity the run
        started with and the one board_changed just read, identity_check.board_restart): the reason
        the run ends error, naming the cause. The restart is counted on the link (the driver did,
        LinkStats.board_restarts) and that count goes with the run."""
        drv = self.slots.driver_of(d.slot)
        now = getattr(drv, "identity", None)
        if drv is None or d.identity is None or now is None:
            return None
        restart = board_restart(d.identity, now)
        if restart is None:
            return None
        if d.link_stats:  # taken at STOP, before the identity that showed the restart was read
            d.link_stats["board_restarts"] = drv.stats.board_restarts
        return f"{d.slot}: {restart}"

    async def release_duts(self, seq: Sequencer) -> None:
        """Stop the batch's streams and boards, set every DUT's end state, then judge every run."""
        await self.slots.stop_streams(seq)
        finished = (seq.ending or seq.state) == "finished"
        # A DUT whose data the database did not take is not 'done' (nor is the batch 'finished').
        why = await self.storage.stored_before_end() if finished else None
        if why is not None:
            seq.storage_error = why

        async def stop_one(d: DutRun) -> None:
            answered = await self.slots.stop_board(d)
            changed = await self.slots.board_changed(d, "at the end of its run") \
                if d.live and finished and why is None else None
            if changed is None and d.live and finished and why is None:
                changed = self._restarted(d)
            if d.live:
                if why is not None:
                    d.state, d.fault_reason = "faulted", f"results not stored: {why}"
                elif changed is not None:
                    d.state, d.fault_reason = "faulted", changed
                elif finished:
                    d.state = "done"
                else:  # every end carries a reason: the batch's own
                    d.state = "interrupted"
                    d.fault_reason = f"batch {seq.ending or seq.state}: {seq.error or 'no reason given'}"
                self.slots.publish_dut(seq, d)
            # the DUT's run faulted (analysis, label, a step, a verification...) on a link that is
            # still there: once the board identifies, the slot is ready for the next batch; the run
            # keeps its fault (at most identify_timeout_s for a board that is mute)
            await self.slots.slot_free(d, answered, self.shutting_down())

        await asyncio.gather(*(stop_one(d) for d in seq.duts))
        moment.judge_final(self.verdicts, seq)  # the verdict's moment: every run, once, from its final state
