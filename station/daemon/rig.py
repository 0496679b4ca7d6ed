"""The sequencer's `Hardware` (station/daemon/sequencer.py): the station's instruments and the two
parts that work the slots, put together once the station has started.

The sequencer drives steps, positions and the lamp; what happens to the boards at a batch's start
and end belongs to the slot bank (slots.py) and the run's end (run_end.py). `Rig` hands each of the
sequencer's calls straight to the part that does it, so a call never goes back up through the
Station facade (supervisor.py), which only builds the Rig when its instruments are connected.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.base import Chamber, Fixture
from station.daemon.dut_run import DutRun
from station.daemon.run_end import RunEnd
from station.daemon.safety import LampGuard
from station.daemon.sequencer import Sequencer
from station.daemon.slots import SlotBank


@dataclass
class Rig:
    """The instruments of a started station and the parts that work its slots (a sequencer.Hardware)."""

    lamp: LampGuard
    fixture: Fixture | None
    chamber: Chamber | None
    fixture_timeout_s: float
    plate_again_after_s: float
    speed: float
    slots: SlotBank
    run_end: RunEnd

    async def connect_duts(self, seq: Sequencer) -> None:
        await self.slots.connect_duts(seq)

    def fault_dut(self, seq: Sequencer, dut: DutRun, reason: str) -> None:
        self.slots.fault_dut(seq, dut, reason)

    async def program_duts(self, seq: Sequencer) -> None:
        await self.run_end.program_duts(seq)

    async def analyse(self, seq: Sequencer) -> None:
        await self.run_end.analyse(seq)

    async def release_duts(self, seq: Sequencer) -> None:
        await self.run_end.release_duts(seq)
