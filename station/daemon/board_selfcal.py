"""The boards' own calibrators as a second opinion (issue 42, a profile's `board_selfcal` option).

A board whose identity reports the capability `scal` runs martinez2022 3.3 itself (design 3.1,
`$SCAL/$SCRR`, its `G` segment frames). With the option on, the sequencer (sequencer.py) asks this
module, through `BoardCalibrators`:
  start(links, duts)   before the thermal steps: every capable board's calibrator on ($SCAL,1,
                       which restarts it), stale `G` frames dropped; a board without the capability
                       is noted (the check is then not applicable: never a fail)
  finish(links, duts)  once the thermal steps are over (before the analysis or the program step):
                       each capable board's result ($SCRR) and the segments it reported, read while
                       it still streams; a board a few samples behind the station (its last segment
                       not saved yet) is asked again for up to FINISH_WAIT_S; then its calibrator off
  compare(duts)        after the analysis: the board's figures against the station's result
                       (station/science/selfcal_compare.py, in a worker thread), per DUT
With the option off every call does nothing. The verdict's moment reads `opinion_of(slot)` (station/decisions/moment.py) for the check
`board_selfcal_agrees`: a capable board whose result could not be read, on the option, is an
error opinion (never a pass).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from contracts.json_safe import JsonDict
from contracts.run_records import ThermalReport
from contracts.selfcal_opinion import BoardSegment, BoardSelfCalReading, SelfCalOpinion
from drivers.base import BoardDriver, BoardSelfCalResult, DriverError
from station.daemon.dut_run import DutRun
from station.science.selfcal_compare import compare

log = logging.getLogger(__name__)

FINISH_WAIT_S = 10.0  # wall seconds a board may take to save the segment the station already logged
POLL_S = 0.25


class BoardLinks(Protocol):
    """The slots' board drivers (slots.SlotBank is one)."""

    def driver_of(self, slot: str) -> BoardDriver | None: ...


@runtime_checkable
class HasBoardLinks(Protocol):
    """The sequencer's hardware when it can reach the slots' drivers (rig.Rig is one: its `slots`)."""

    @property
    def slots(self) -> BoardLinks: ...


def links_of(hw: object) -> BoardLinks | None:
    """The slots' drivers behind the sequencer's hardware (None: a hardware without slots, a test's)."""
    return hw.slots if isinstance(hw, HasBoardLinks) else None


def _caps_words(drv: BoardDriver) -> str:
    caps = sorted(drv.identity.caps) if drv.identity is not None else []
    return "+".join(caps) if caps else "none"


class BoardCalibrators:
    """The boards' calibrators of one batch (module doc): readings and opinions per slot."""

    def __init__(self, enabled: bool, resumed_at_step: int = 0) -> None:
        self.enabled = enabled  # the profile's option: off, every call does nothing
        self.resumed_at_step = resumed_at_step
        self.readings: dict[str, BoardSelfCalReading] = {}
        self.opinions: dict[str, SelfCalOpinion] = {}
        self._started: dict[str, str | None] = {}  # slot -> None (on) or why it could not be switched on
        self._segments: dict[str, list[BoardSegment]] = {}
        self.finished = False
        self.compared = False

    # ---- before the thermal steps -------------------------------------------------------------
    async def start(self, hw: object, duts: Sequence[DutRun]) -> None:
        if not self.enabled:
            return
        links = links_of(hw)

        async def one(d: DutRun) -> None:
            drv = links.driver_of(d.slot) if links is not None else None
            if drv is None:
                self._started[d.slot] = "no board link to switch its calibrator on"
                return
            if not drv.supports_selfcal:
                self.readings[d.slot] = BoardSelfCalReading(
                    False, note=f"{d.link or d.slot}: the board's identity reports no on-board calibrator "
                                f"(caps: {_caps_words(drv)}; 'scal' needed)")
                return
            if self.resumed_at_step > 0:
                self._started[d.slot] = (f"the batch was resumed at step {self.resumed_at_step}: the board's calibrator "
                                         "did not see the steps before")
                return
            try:
                await drv.set_selfcal(True)
                drv.take_selfcal_segments()  # frames of an earlier run are not this run's
                self._started[d.slot] = None
                self._segments[d.slot] = []
            except DriverError as exc:
                self._started[d.slot] = f"$SCAL,1 failed: {exc}"
                log.warning("slot %s: board calibrator not switched on: %s", d.slot, exc)

        await asyncio.gather(*(one(d) for d in duts if d.live))

    # ---- after the thermal steps ----------------------------------------------------------------
    async def finish(self, hw: object, duts: Sequence[DutRun], wait_s: float = FINISH_WAIT_S) -> None:
        if not self.enabled or self.finished:
            return
        self.finished = True
        links = links_of(hw)

        async def one(d: DutRun) -> None:
            if d.slot in self.readings:  # not capable: noted at the start
                return
            why = self._started.get(d.slot, "its calibrator was not switched on at the start")
            drv = links.driver_of(d.slot) if links is not None else None
            if why is not None or drv is None:
                self.readings[d.slot] = BoardSelfCalReading(True, error=why or "no board link to read its result")
                return
            segs = self._segments.setdefault(d.slot, [])
            loop = asyncio.get_running_loop()
            end = loop.time() + wait_s
            res: BoardSelfCalResult | None = None
            failed: DriverError | None = None
            while True:  # a board a few samples behind the station: its last segment comes within wait_s
                segs += [BoardSegment(f.index, f.orientation, f.t_end_us, f.acc_g, f.temp_c, f.n)
                         for f in drv.take_selfcal_segments()]
                try:
                    res, failed = await drv.read_selfcal(), None
                except DriverError as exc:  # E,SCRR (no result yet, or none), no reply, ...
                    res, failed = None, exc
                if (res is not None and res.n_segments >= len(d.segments)) or loop.time() >= end:
                    break
                await asyncio.sleep(POLL_S)
            segs += [BoardSegment(f.index, f.orientation, f.t_end_us, f.acc_g, f.temp_c, f.n)
                     for f in drv.take_selfcal_segments()]
            if res is None:
                self.readings[d.slot] = BoardSelfCalReading(True, error=f"$SCRR failed: {failed}", segments=tuple(segs))
                log.warning("slot %s: board calibrator not read: %s", d.slot, failed)
                return
            self.readings[d.slot] = BoardSelfCalReading(
                True, res.tdb_mg_per_c, res.tdsf_ppm_per_c, res.n_segments, res.clamped_axes, tuple(segs))
            try:
                await drv.set_selfcal(False)  # its work is done; the board needs its cycles
            except DriverError:
                pass

        await asyncio.gather(*(one(d) for d in duts if d.live))

    # ---- after the analysis --------------------------------------------------------------------
    async def compare(self, duts: Sequence[DutRun]) -> None:
        """Each read board's figures against the station's result (worker thread; see module doc)."""
        if not self.enabled or self.compared:
            return
        self.compared = True
        work = [(d.slot, r, d.result, list(d.segments), d.identity.odr_hz, d.identity.sensor)
                for d in duts if (r := self.readings.get(d.slot)) is not None and r.has_result
                and isinstance(d.result, ThermalReport) and d.identity is not None]

        def run() -> dict[str, SelfCalOpinion]:
            return {slot: compare(r, rep.axes, rep.uncertainty, segs, odr, sensor)
                    for slot, r, rep, segs, odr, sensor in work}

        self.opinions.update(await asyncio.to_thread(run))
        for d in duts:  # beside the station's result on the live status (slots[].result.board_selfcal)
            op = self.opinions.get(d.slot)
            if op is not None and isinstance(d.result, ThermalReport):
                d.result = ThermalReport.from_json({**d.result.to_json(), "board_selfcal": op.to_json()})

    def opinion_of(self, slot: str) -> JsonDict:
        """The opinion the verdict judges for this slot (module doc): compared, or why not."""
        op = self.opinions.get(slot)
        if op is None:
            r = self.readings.get(slot)
            if r is None:
                op = SelfCalOpinion(True, error="the board's calibrator was not read at the end of the thermal steps")
            elif not r.capable:
                op = SelfCalOpinion(False, note=r.note)
            elif not r.has_result:
                op = SelfCalOpinion(True, error=r.error or "the board gave no result", n_segments_board=r.n_segments)
            else:
                op = SelfCalOpinion(True, error="no station result to compare the board's with",
                                    n_segments_board=r.n_segments)
        return op.to_json()


__all__ = ["BoardCalibrators", "BoardLinks", "HasBoardLinks", "links_of", "FINISH_WAIT_S"]
