"""Temperature sensor faults of a simulated world's boards, armed by tests.

SimWorld.stick_temp_sensor / temp_sensor_reads / heal_temp_sensor (drivers/sim/world.py) arm and
clear them; the world hands every chunk's temperature counts through `apply()`, so a serial board
and a CAN board alike report the faulty counts (both send the counts the world makes). The die and
the MEMS go on heating: only what the sensor reports is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class _Fault:
    from_s: float  # sample time the fault starts at
    count: int | None  # the count reported from then on (None: stuck, taken from the reading before)


class TempSensorFaults:
    """The armed fault of each DUT (by index) and each DUT's latest reported count."""

    def __init__(self, n_duts: int) -> None:
        self._faults: dict[int, _Fault] = {}
        self._last_count: list[int | None] = [None] * n_duts

    def arm(self, i: int, from_s: float, count: int | None) -> None:
        """DUT i's sensor reports `count` from sample time from_s on (None: stuck at the reading
        before from_s)."""
        self._faults[int(i)] = _Fault(float(from_s), count)

    def heal(self, i: int) -> None:
        self._faults.pop(int(i), None)

    def apply(self, i: int, time_s: np.ndarray, counts: np.ndarray) -> None:
        """DUT i's counts of one chunk (sample times time_s): its armed fault applied in place,
        and the last one noted (a sensor that sticks at a chunk's start repeats it)."""
        if self._faults:
            self._apply(i, time_s, counts)
        if counts.size:
            self._last_count[i] = int(counts[-1])

    def _apply(self, i: int, time_s: np.ndarray, counts: np.ndarray) -> None:
        fault = self._faults.get(i)
        if fault is None or not counts.size:
            return
        m = int(np.searchsorted(time_s, fault.from_s - 1e-9))
        if m >= counts.size:
            return
        if fault.count is None:  # stuck at the reading before from_s (the chunk's first if none came before)
            prev = counts[m - 1] if m > 0 else self._last_count[i]
            fault.count = int(counts[m] if prev is None else prev)
        counts[m:] = fault.count
