"""The run's end: analysis, program-and-verify, each DUT's end state, then the verdict's moment.

The sequencer calls these when its batch reaches them:
- `analyse`: the calibration result of every live DUT with data (thermal or SFEM, two at a time
  in worker threads so the pumps of other batches keep their core), published WITHOUT a verdict;
  after a programming step, the verification instead (station/daemon/program_verify.py);
- `release_duts`: the pumps stop, the boards stop, everything stored so far must be committed, and
  each live DUT gets its end state (done; interrupted with the batch's reason; faulted when its data
  were not stored); a slot whose DUT faulted but whose board still answers is ready again
  (`identified`) for the next batch. Only then is every run judged, once, from that final state
  (station/decisions/moment.judge_final): no fault, abort or failed verification can come after a
  verdict and leave a pass behind (design 8).
"""

from __future__ import annotations

import asyncio
from typing import Any

from contracts.events import DutResult
from contracts.types import StationError
from station.daemon import program_verify
from station.daemon.results import sfem_result, thermal_result
from station.daemon.dut_run import DutRun
from station.daemon.sequencer import Sequencer
from station.daemon.slots import board_changed, publish_dut, ready_again, stop_streams
from station.decisions import moment

ANALYSIS_THREADS = 2  # two cores: do not starve the pumps of other work


async def analyse(st: Any, seq: Sequencer) -> None:
    if program_verify.after_programming(seq):  # the first pass was analysed in the program step
        await program_verify.verify_duts(st, seq)
        return
    if not st.analyse_results:
        return
    kind = seq.profile.analysis
    duts = [d for d in seq.duts if d.live and d.n_samples > 0]
    if kind == "none" or not duts:
        return
    sem = asyncio.Semaphore(ANALYSIS_THREADS)

    async def one(d: DutRun) -> None:
        async with sem:
            try:
                if kind == "thermal":
                    full_range_c = moment.operating_range_c(st.verdicts, d.identity, seq.trace.part_number)
                    res = await asyncio.to_thread(thermal_result, d, full_range_c)
                    d.result = res
                    st.bus.publish(DutResult(seq.batch_id, slot=d.slot, serial=d.serial or "", thermal=res))
                elif kind == "sfem":
                    res = await asyncio.to_thread(sfem_result, d, seq.profile)
                    d.result = res
                    st.bus.publish(DutResult(seq.batch_id, slot=d.slot, serial=d.serial or "", sfem=res))
            except StationError as exc:  # InsufficientData and friends: this DUT only
                st.fault_dut(seq, d, f"analysis: {exc}")

    await asyncio.gather(*(one(d) for d in duts))


async def release_duts(st: Any, seq: Sequencer) -> None:
    """Stop the batch's streams and boards, set every DUT's end state, then judge every run."""
    await stop_streams(st, seq)
    finished = (seq.ending or seq.state) == "finished"
    # A DUT whose data the database did not take is not 'done' (nor is the batch 'finished').
    why = await st.storage.stored_before_end() if finished else None
    if why is not None:
        seq.storage_error = why

    async def stop_one(d: DutRun) -> None:
        slot = st.slots[d.slot]
        answered = False  # the STOP went out (a serial board acknowledges it): the link is still there
        if slot.driver is not None:
            try:
                await asyncio.wait_for(slot.driver.stop(), 3.0)
                answered = True
            except Exception:
                pass
            d.link_stats = slot.driver.stats.as_dict() if hasattr(slot.driver, "stats") else {}
        changed = await board_changed(st, d, "at the end of its run") if d.live and finished and why is None else None
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
            publish_dut(st, seq, d)
        if slot.state == "busy":
            slot.state = "identified"
        elif slot.state == "faulted" and answered and getattr(st, "running", True):  # not at a shutdown
            # the DUT's run faulted (analysis, label, a step, a verification...) on a link that is
            # still there: once the board identifies, the slot is ready for the next batch; the run
            # keeps its fault (slots.ready_again; at most identify_timeout_s for a board that is mute)
            await ready_again(st, slot)

    await asyncio.gather(*(stop_one(d) for d in seq.duts))
    moment.judge_final(st.verdicts, seq)  # the verdict's moment: every run, once, from its final state
