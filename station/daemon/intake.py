"""The data path of one running DUT: read its link, take each sample block in, feed the calibrator.

`pump` is one task per DUT: it reads blocks at a steady pace (big enough that the calibrator's
batch update is cheap; each link less often when many share the loop: intake_monitor.read_pace_s)
until the batch releases its DUTs, and turns every link problem into a
fault of this DUT alone, with the reason the operator reads: link lost, no samples for N s, only
garbage (bad frames, no good one), a driver bug. "No samples" counts only the time the board had
the chance to send: not while the station itself has stopped the streams to program the boards,
and not the time the station's own loop was held up (a slow database call, a long collection):
each read adds at most `listen_cap_s` to the silence, so a host hiccup never faults a good board,
and a dead board is still faulted after stall_timeout_s of listening. `ingest` is what one block does: publish it (the
database writer stores it), keep it for the offline fit, feed the streaming calibrator and publish
the segments it logs, and show the lamp guard the DUT's temperature.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Protocol

import numpy as np

from contracts.events import EventBus, SamplesReceived, SegmentLogged
from contracts.types import SampleBlock
from drivers.base import BoardDriver, DriverError
from station.config import Timing
from station.daemon.dut_run import DutRun, annotate_segment
from station.daemon.intake_monitor import IntakeMonitor
from station.daemon.safety import LampGuard
from station.daemon.sequencer import Sequencer
from station.science.placement import direction_id, label_cuts, same_direction

log = logging.getLogger(__name__)


class IntakeHost(Protocol):
    """What a DUT's pump needs of the station (slots.SlotBank is one): where its samples go, the
    lamp that must hear of every sample's temperature, the read pace, and how to fault its DUT."""

    bus: EventBus
    timing: Timing
    lamp: LampGuard | None
    monitor: IntakeMonitor

    def fault_dut(self, seq: Sequencer, d: DutRun, reason: str) -> None: ...

    def releasing(self, batch_id: int) -> bool: ...


class Link(Protocol):
    """A slot's link as its pump holds it (slots.SlotRuntime is one): the driver, closed on a fault."""

    driver: BoardDriver | None

    async def close_driver(self) -> None: ...


async def pump(st: IntakeHost, seq: Sequencer, d: DutRun, slot: Link) -> None:
    """Read one DUT's link until the batch ends; fault only this DUT on a link problem."""
    drv = slot.driver
    assert drv is not None
    timing = st.timing
    period = timing.read_period_s
    stats = drv.stats
    bad0 = stats.frames_bad_checksum + stats.frames_malformed + stats.bytes_skipped
    ok0 = stats.frames_ok
    read_timeout_s = max(period, 0.25)
    silent_s = 0.0  # wall seconds this board had the chance to send and sent nothing
    t_prev = time.monotonic()
    queue0 = stats.samples_lost_queue
    t_read_prev = t_read_last = t_prev  # when this pump's previous and latest reads returned
    st.monitor.forget(d.slot)  # a new run: its link's lag is learned again
    st.monitor.pumping.add(d.slot)
    rate = 0.0  # samples per wall second this link has been sending (the read pace's input)
    try:
        while d.live and not st.releasing(seq.batch_id):
            t_read = time.monotonic()
            try:
                block = await drv.read_block(timeout_s=read_timeout_s)
            except DriverError as exc:
                st.fault_dut(seq, d, f"{d.link}: link lost: {exc}")
                await slot.close_driver()
                return
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - a driver bug must fault its slot, never kill the pump silently
                log.exception("slot %s: reading %s failed", d.slot, d.link)
                st.fault_dut(seq, d, f"{d.link}: board data could not be read: {type(exc).__name__}: {exc}")
                await slot.close_driver()
                return
            now = time.monotonic()
            if len(block):  # smoothed: one short or long read does not flip the pace
                sent = len(block) / max(now - t_read_last, 1e-3)
                rate = sent if rate == 0.0 else 0.8 * rate + 0.2 * sent
            pace = st.monitor.pace_s(period, rate)  # small reads of many links: spaced out (read_pace_s)
            chance_s, t_prev = min(now - t_prev, listen_cap_s(pace)), now
            t_read_prev, t_read_last = t_read_last, now
            if len(block):
                queue0 = _note_lag(st.monitor, d, drv, block, queue0, now, now - t_read_prev - pace)
                try:
                    ingest(st, seq, d, block)
                except Exception as exc:  # noqa: BLE001 - same: this slot only, with a reason
                    log.exception("slot %s: processing a block from %s failed", d.slot, d.link)
                    st.fault_dut(seq, d, f"{d.link}: board data could not be processed: {type(exc).__name__}: {exc}")
                    await slot.close_driver()
                    return
                bad0 = stats.frames_bad_checksum + stats.frames_malformed + stats.bytes_skipped
                ok0 = stats.frames_ok
                silent_s = 0.0
            elif seq.state == "programming":
                # the program step stops every stream to write the calibration (program_verify.py);
                # a board that does not answer there is faulted by the write, with that reason
                silent_s = 0.0
            else:
                silent_s += chance_s
                if silent_s > timing.stall_timeout_s:
                    bad = stats.frames_bad_checksum + stats.frames_malformed + stats.bytes_skipped - bad0
                    if bad > 0 and stats.frames_ok == ok0:
                        reason = (f"{d.link}: only garbage for {silent_s:.1f} s "
                                  f"({bad} bad frames/bytes, no good frame)")
                    else:
                        reason = f"{d.link}: no samples for {silent_s:.1f} s"
                    st.fault_dut(seq, d, reason)
                    return
            breaks = drv.take_breaks()
            if breaks:  # a reset or a clock jump: the samples before it are the run's, nothing after
                st.fault_dut(seq, d, breaks[0].reason)
                return
            # Pace the reads so that blocks are big enough to be cheap (update_batch).
            rest = pace - (time.monotonic() - t_read)
            if rest > 0:
                await asyncio.sleep(rest)
    finally:
        st.monitor.pumping.discard(d.slot)
        d.link_stats = stats.as_dict()


def _note_lag(monitor: IntakeMonitor, d: DutRun, drv: BoardDriver, block: SampleBlock, queue0: int,
              now: float, late_s: float) -> int:
    """Tell the monitor how late this block comes and what its link lost; the losses the station
    caused (gaps while it ran behind, its driver's full queue) are counted on the link and kept on
    the run (the step clock does not count their sample time: dut_run.step_elapsed_s). Returns the
    queue-drop counter now."""
    stats = drv.stats
    dropped = stats.samples_lost_queue - queue0
    gaps = max(0, block.lost_samples - dropped)
    odr = d.identity.odr_hz if d.identity and d.identity.odr_hz else None
    ours = monitor.note_block(d.slot, now, drv.backlog_samples(), len(block), gaps, odr, late_s) + dropped
    monitor.note_dropped(d.slot, dropped, now)
    d.link_behind_s = monitor.behind_s(d.slot)
    if ours:
        stats.samples_lost_station += ours
        d.station_lost_samples += ours
        d.station_lost_s += ours / odr if odr else 0.0
    return stats.samples_lost_queue


def listen_cap_s(read_period_s: float) -> float:
    """The most one read may add to a board's silence: a read waits max(period, 0.25 s) and the
    pump then sleeps out the period, so a turn longer than twice that plus half a second is the
    station's own loop running late, not the board being quiet."""
    return 2.0 * max(read_period_s, 0.25) + 0.5


def ingest(st: IntakeHost, seq: Sequencer, d: DutRun, block: SampleBlock) -> None:
    if d.resume_t is not None:
        # First block after a resume: a board whose clock restarted (CAN time is sample index /
        # ODR from our own count) is joined on one sample period after the stored stream.
        if block.time_s[0] <= d.resume_t:
            odr = d.identity.odr_hz if d.identity and d.identity.odr_hz else 1.0
            d.time_offset_s = d.resume_t + 1.0 / odr - float(block.time_s[0])
        d.resume_t = None
    if d.time_offset_s:
        block = SampleBlock(block.time_s + d.time_offset_s, block.acc_g, block.temp_c, block.lost_samples)
    if d.t0 is None:
        d.t0 = float(block.time_s[0])
    d.last_t = float(block.time_s[-1])
    d.n_samples += len(block)
    # Placement (station/science/placement.py, docs/design.md section 4): what each sample measured
    # decides where it was, never the button or the fixture's bit. The block is cut where that changes.
    labels = place(d, block)
    for a, b in label_cuts(labels):
        part = block if (a, b) == (0, len(block)) else SampleBlock(
            block.time_s[a:b], block.acc_g[a:b], block.temp_c[a:b], block.lost_samples if a == 0 else 0)
        _take(st, seq, d, part, int(labels[a]) if labels[a] >= 0 else None)
    lamp = st.lamp
    assert lamp is not None
    lamp.note_sample_time(seq.clock_s())
    # A stuck or implausible temperature sensor faults this DUT alone, and a reading it cannot
    # believe trips no lamp for the plate (station/daemon/temp_watch.py).
    hot_c, finding = d.watch_temp(block, lamp.is_on, seq.live_duts, lamp.plate_temp_c)
    if finding is not None:
        st.fault_dut(seq, d, finding.reason)
    elif hot_c is not None:
        lamp.check_dut_temp(d.slot, hot_c)
    seq.notify()


def place(d: DutRun, block: SampleBlock) -> np.ndarray:
    """Per sample, the position it is placed at (-1: none): settled at the step's position; at the
    position of the step before until the DUT has arrived at the new one (the plate sits there
    until somebody or the fixture moves it); or at the next step's (the plate moved on while this
    block still held the end of the step). The roles are set at each step's setup, so the labels
    depend on the samples alone, never on when Done or "reached" came: a replay of the same samples
    gets the same labels, fits and results."""
    ids, settled = d.placement.update(block.time_s, block.acc_g)
    if d.first_settled is None:
        d.first_settled = d.placement.settled_direction()
    labels = np.full(len(block), -1, dtype=np.int64)
    if d.step_position is None:
        return labels
    here = settled & (ids == direction_id(d.step_position))
    if d.next_position is not None and not same_direction(d.next_position, d.step_position):
        labels[settled & (ids == direction_id(d.next_position))] = d.next_position
    if d.prev_position is not None and d.arrived_t is None and not same_direction(d.prev_position, d.step_position):
        before = settled & (ids == direction_id(d.prev_position))
        hit = np.flatnonzero(here)
        if hit.size:
            before[hit[0]:] = False  # arrived in this block: the old position no longer counts
        labels[before] = d.prev_position
    labels[here] = d.step_position
    return labels


def _take(st: IntakeHost, seq: Sequencer, d: DutRun, block: SampleBlock, position: int | None) -> None:
    """One run of equally placed samples: keep it, publish it with its position (None: not placed,
    stored as -1), track the step's arrival and departures, and feed the calibrator placed samples
    only, its averaging window starting over after every gap or change of position."""
    d.blocks.append(block)
    d.block_steps.append(seq.step_index)
    d.block_positions.append(-1 if position is None else int(position))
    lamp = st.lamp
    assert lamp is not None
    st.bus.publish(SamplesReceived(seq.batch_id, slot=d.slot, serial=d.serial or "", step_index=seq.step_index,
                                   block=block, lamp_on=lamp.is_on, position=position))
    was_at_step = d.at_step_position()
    if position is None or d.placed_at != position:
        if position is None:
            d.placed_since_t = d.placed_at = None
        else:
            d.placed_since_t, d.placed_at = float(block.time_s[0]), int(position)
        d.fed_last = False
    if was_at_step and not d.at_step_position():
        d.left_t = float(block.time_s[0])
    if d.at_step_position() and d.arrived_t is None:
        d.arrived_t = d.placed_since_t
    if position is None:
        return
    if d.hold_calibrator and seq.state == "logging":
        # Resumed: the plate is where the step wants it now. No average may span the time the
        # daemon was down or the reconnect, so the calibrator's window starts over here.
        d.hold_calibrator = False
        d.fed_last = False
    if d.calibrator is None or d.hold_calibrator:
        return
    if not d.fed_last:
        d.calibrator.restart_window()  # no average spans samples that were not placed here
    d.fed_last = True
    for seg in d.calibrator.update_batch(block.time_s, block.acc_g, block.temp_c):
        seg = annotate_segment(seg, position)
        d.segments.append(seg)
        d.segment_steps.append(seq.step_index)
        st.bus.publish(SegmentLogged(seq.batch_id, slot=d.slot, serial=d.serial or "",
                                     step_index=seq.step_index, segment=seg))
