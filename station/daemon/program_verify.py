"""Program and verify (design 4): write the calibration into every board, prove it is stored, and
measure that the compensation works on the part.

The run's end (run_end.RunEnd) calls the two entry points, each with a `ProgramHost` (the slot
bank: what these need of the slots, nothing more):
  program_duts(host, seq)     the `program` step, after the first pass's thermal analysis: per live
                              DUT in parallel: stop its stream and let the link drain, write
                              TDB/TDSF, read back and compare CRC and values, switch on-board
                              compensation on and confirm it (BoardDriver.program_thermal, 3
                              tries), start the stream again (compensated). A DUT without a thermal result or whose
                              write fails (CRC mismatch, refused, no reply, read-back differs) is
                              faulted ALONE with the named reason; the others go on.
  verify_duts(host, seq)      at the end of the batch: for every programmed DUT, the compensated
                              samples from its restart + the heat step's settle time until its own
                              temperature has risen heat_c (rise_window: sample-defined) ->
                              station.science.verify.verify_compensated, with the uncompensated E of
                              the same orientation from the first pass as "before".
Both publish events (DutProgrammed, DutVerified) that the writer stores and the web shows; neither
judges: the run's verdict is decided once at its end (station/decisions/moment.py), from these records.
After an SFEM analysis both hand over to station/daemon/sfem_program.py (issue 42: the cubic SFEM
as the board's version-2 record, verified on a cool-down), with the same host and conventions.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from drivers.base import BoardDriver, CalibrationError, DriverError
from contracts.events import DutProgrammed, DutVerified, EventBus
from contracts.run_records import ProgramRecord, ThermalReport
from station.science.bias_wander import BiasWander
from station.science.part_noise import wander_of_budget
from station.science.verify import drift_before_mg, verify_compensated
from contracts.types import AXES, SampleBlock, Segment
from station.daemon import sfem_program
from station.daemon.dut_run import DutRun
from station.daemon.sequencer import Sequencer
from station.profiles import Profile

log = logging.getLogger(__name__)


class ProgramHost(Protocol):
    """What program and verify need of the station (slots.SlotBank is one): the board of a slot, its
    identity read again, a DUT faulted alone, and where the records go."""

    bus: EventBus

    def driver_of(self, slot: str) -> BoardDriver | None: ...

    async def board_changed(self, d: DutRun, when: str) -> str | None: ...

    def fault_dut(self, seq: Sequencer, d: DutRun, reason: str) -> None: ...


def uses_program_verify(profile: Profile) -> bool:
    return profile.program_step is not None


def after_programming(seq: Sequencer) -> bool:
    """True once the batch is past its program step (the end-of-batch analysis is the verification)."""
    ps = seq.profile.program_step
    return ps is not None and seq.step_index > ps


QUIET_S = 0.3  # the link is drained when nothing arrived for this long
DRAIN_MAX_S = 20.0


async def _quiesce(drv: BoardDriver) -> bool:
    """Stop the board's stream and wait until its link is drained, so that the calibration replies
    do not queue behind a backlog of sample frames (a slow host, a busy CAN bus, compressed time):
    the reply timeouts then measure the board, not the backlog. Flash writes stall a board's
    sampling anyway. Returns False if the link never went quiet within DRAIN_MAX_S."""
    try:
        await drv.stop()
    except DriverError:
        pass  # the ack may sit behind the backlog: draining below still applies
    loop = asyncio.get_running_loop()
    end = loop.time() + DRAIN_MAX_S
    while loop.time() < end:
        if time.monotonic() - drv.last_rx_wall >= QUIET_S:
            return True
        await asyncio.sleep(0.05)
    return False


async def program_duts(station: ProgramHost, seq: Sequencer) -> None:
    """The program step (see module doc): the first pass is analysed already (run_end.RunEnd)."""
    if seq.profile.analysis == "sfem":
        await sfem_program.program_sfem_duts(station, seq, _quiesce)
        return
    duts = [d for d in seq.duts if d.live]

    async def one(d: DutRun) -> None:
        # Every DUT with a result is written and verified, whatever its first-pass verdict: the
        # verification is measured evidence (a part the fit already rejects for curvature shows
        # its residual drift), and the final verdict takes both (station/decisions/moment.py judge_final).
        report = d.result if isinstance(d.result, ThermalReport) else None
        coeffs = report.coefficients() if report is not None else None
        if report is None or coeffs is None:
            d.program = ProgramRecord(False, error_kind="no_result", error="no thermal result to write")
            station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=d.program))
            station.fault_dut(seq, d, "program: no thermal result to write")
            return
        tdb, tdsf = coeffs
        drv = station.driver_of(d.slot)
        if drv is not None:
            await _quiesce(drv)
            # the coefficients are this board's only if it is still the board the run measured
            changed = await station.board_changed(d, "before programming")
            if changed is not None:
                d.program = ProgramRecord(False, error_kind="identity", error=changed)
                station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=d.program))
                station.fault_dut(seq, d, f"program: not written: {changed}")
                return
        written = ProgramRecord(False, tdb_mg_per_c=tuple(tdb), tdsf_ppm_per_c=tuple(tdsf), method=report.axes_method)
        try:
            if drv is None:
                raise DriverError(f"{d.link}: link closed")
            rep = await drv.program_thermal(tdb, tdsf, compensation=True)
        except CalibrationError as exc:
            d.program = info = replace(written, error_kind=exc.kind, error=str(exc), attempts=exc.attempts, comp=False)
            station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=info))
            station.fault_dut(seq, d, f"program: {exc.kind}: {exc}")
            return
        except DriverError as exc:
            d.program = info = replace(written, error_kind="link", error=str(exc), comp=False)
            station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=info))
            station.fault_dut(seq, d, f"program: link: {exc}")
            return
        board = rep.to_json()
        d.program = info = replace(written, programmed=True, attempts=rep.attempts, comp=rep.comp,
                                   readback={k: v for k, v in board.items() if k not in ("attempts", "comp")})
        try:
            await drv.start()  # streaming again, now compensated
        except DriverError as exc:
            station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=info))
            station.fault_dut(seq, d, f"program: restart after programming failed: {exc}")
            return
        if rep.retries:
            log.warning("batch %d slot %s programmed after retries: %s", seq.batch_id, d.slot, "; ".join(rep.retries))
        station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=info))

    await asyncio.gather(*(one(d) for d in duts))


def _verify_one(blocks: list[tuple[SampleBlock, int]], segments: list[tuple[Segment, int]], t_start: float,
                t_end: float | None, profile: Profile, heat_index: int, program_index: int,
                comp_from_t: float | None = None, wander: BiasWander | str = "auto") -> dict[str, Any]:
    """Pure part of the verification of one DUT (runs in a worker thread on snapshots):
    blocks = [(SampleBlock, step index)], segments = [(Segment, step index)]; wander: the part's own
    bias wander from its calibration (`wander_of_budget`), "auto" to measure it here."""
    step = profile.steps[heat_index]
    if comp_from_t is not None:
        block = SampleBlock.concat([b for b, st in blocks if st >= program_index])
        m = rise_window(block.time_s, block.temp_c, comp_from_t + step.settle_s, step.heat_c)
    else:  # no program record of the restart point: the step's own window (as the sequencer saw it)
        block = SampleBlock.concat([b for b, st in blocks if st == heat_index])
        t0 = t_start + step.settle_s if np.isfinite(t_start) else -np.inf
        m = block.time_s > t0
    segs = [(s.t_end_s, s.acc_mean_g, s.temp_mean_c) for s, st in segments
            if st < program_index and s.position == step.position]
    segs.sort(key=lambda x: x[0])
    before = None
    if len(segs) >= 2:
        before = drift_before_mg(np.array([s[1] for s in segs]), np.array([s[2] for s in segs]),
                                 profile.verify.full_range_c)
    res = verify_compensated(block.acc_g[m], block.temp_c[m], before, profile.verify, time_s=block.time_s[m],
                             wander=wander)
    out = res.to_json()
    out["step_index"] = heat_index
    out["duration_s"] = float(t_end - t_start) if np.isfinite(t_start) and t_end is not None else None
    out["before_source"] = (f"{len(segs)} first-pass segment(s) at position {step.position_name}, uncompensated"
                            if before is not None else "none: fewer than two first-pass segments at this position")
    return out


def rise_window(time_s: np.ndarray, temp_c: np.ndarray, t_from: float, heat_c: float, n_edge: int = 8) -> np.ndarray:
    """Mask of the verification window: the compensated samples after t_from (the board's
    restart after programming + the step's settle time) until this DUT's own temperature has risen
    heat_c (median of n_edge samples against the first n_edge, as the sequencer's heat step
    measures a rise), or all of them if it never did.

    Both ends are defined by the samples, not by when the daemon happened to read them: the heat
    step starts when the last board is programmed and ends when the last DUT has risen, which in
    compressed time moves by a read block (tens of sample seconds). So a live run, a replay of it
    and the same samples from a file give the same E."""
    t = np.asarray(time_s, dtype=np.float64)
    m = t > t_from
    idx = np.flatnonzero(m)
    if len(idx) < 2 * n_edge:
        return m
    temps = np.asarray(temp_c, dtype=np.float64)[idx]
    ref = float(np.median(temps[:n_edge]))
    rolling = np.median(np.lib.stride_tricks.sliding_window_view(temps, n_edge), axis=1)
    hit = np.flatnonzero(rolling - ref >= heat_c)
    if len(hit):
        m[idx[hit[0] + n_edge - 1] + 1:] = False
    return m


async def verify_duts(station: ProgramHost, seq: Sequencer) -> None:
    """Verified E for every programmed DUT (see module doc); a DUT the verification cannot judge
    gets passed=False with the reason, never a silent pass."""
    profile = seq.profile
    program_index = profile.program_step
    if program_index is None:
        return
    if profile.analysis == "sfem":
        await sfem_program.verify_sfem_duts(station, seq)
        return
    heat_index = next((i for i in range(program_index + 1, len(profile.steps)) if profile.steps[i].require == "heat"), None)
    if heat_index is None:
        return
    duts = [d for d in seq.duts if d.live]

    async def one(d: DutRun) -> None:
        if d.program is None or not d.program.programmed:
            # e.g. a batch resumed after its program step: this session did not program the board,
            # so its output cannot be judged as compensated. Said so, never passed silently.
            out: dict[str, Any] = {"passed": False, "flags": ["no programming record for this run in this session (batch resumed "
                                              "after the program step?): not verified"],
                   "e_before_mg": None, "e_after_mg": None, "axes": {}}
            d.verification = out
            station.bus.publish(DutVerified(seq.batch_id, slot=d.slot, serial=d.serial or "", verification=out))
            return
        try:
            # snapshots taken in the loop (pumps append); every sample: the verification's window is
            # defined by the samples themselves (design 4), the placement labels play no part in it
            blocks = list(zip(d.blocks, d.block_steps))
            segments = list(zip(d.segments, d.segment_steps))
            t_start, t_end = d.step_windows.get(heat_index, (d.step_t_start, d.last_t))
            comp_t = d.program.comp_from_t
            comp_t = None if comp_t is None else comp_t + d.time_offset_s
            budget = d.result.uncertainty if isinstance(d.result, ThermalReport) else None
            wander = wander_of_budget(budget) or "auto"  # the part's, measured raw
            out = await asyncio.to_thread(_verify_one, blocks, segments, t_start, t_end, profile, heat_index,
                                          program_index, comp_t, wander)
        except (ValueError, np.linalg.LinAlgError) as exc:
            out = {"passed": False, "flags": [f"verification could not be computed: {exc}"], "e_before_mg": None,
                   "e_after_mg": None, "axes": {}}
        d.verification = out
        if not out["passed"]:
            log.warning("batch %d slot %s verification failed: %s", seq.batch_id, d.slot, "; ".join(out["flags"]))
        station.bus.publish(DutVerified(seq.batch_id, slot=d.slot, serial=d.serial or "", verification=out))

    await asyncio.gather(*(one(d) for d in duts))


__all__ = ["program_duts", "verify_duts", "uses_program_verify", "after_programming"]
