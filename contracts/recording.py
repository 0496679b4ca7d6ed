"""A recorded batch as a replay plays it back: per DUT the board's counts, identity and sample clock,
the lamp and plate position the station stored beside every sample, and the stored outcome.

A contract between the replay's sources (station/replay/recording.py reads a database or design-5.1
logs into it) and the replay boards (drivers/sim/replay.py stream it), so neither reaches into the
other.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from contracts.types import T_REF_C, Identity, StationError

# The identity of a board replaying a log: one count = the log's stored precision (logfile.py).
LOG_UG_PER_LSB = 0.1
LOG_T_LSB_PER_C = 1e4
COUNT_LIMIT = (1 << 31) - 1  # serial frames carry int32 counts


@dataclass
class RecordedDut:
    """One DUT's recorded stream, ready for a replay board (counts in its identity's LSBs)."""

    slot: str
    serial: str
    link: str  # "serial" or "can"
    identity: Identity
    time_s: np.ndarray  # (n,) the board's own sample clock
    acc_counts: np.ndarray  # (n, 3) int64
    temp_counts: np.ndarray  # (n,) int64
    lamp: np.ndarray | None = None  # (n,) 0/1 as the station recorded it
    position: np.ndarray | None = None  # (n,) -1 while moving/unknown
    lost_samples: int = 0
    source_run_id: int | None = None
    outcome: dict[str, Any] = field(default_factory=dict)  # the stored (or offline) result, see compare.py
    # The board time of the last sample before the station stopped the board to program it (the
    # program record's comp_from_t): the record pauses there until the replaying daemon stops it.
    restart_after_t: float | None = None
    # How the recorded board answered the calibration write when it failed (CAL_ERROR_KINDS): the
    # replay board answers the same way (drivers/sim/replay.py).
    program_error_kind: str | None = None
    # The recorded run was faulted because its link was lost (a board unplugged, a cable pulled):
    # the replay board is unplugged where the record ends, so the replaying daemon faults it at the
    # same point of the stream. (A board that only went silent is faulted by the wall-clock stall
    # timeout, whose point in sample time depends on the speed and the load: not reproducible.)
    unplugged_at_end: bool = False
    # The board time at which the recorded station began each step (its DutRun.step_t_start: the
    # last sample it had taken when the step began logging; the batch's step_windows). A replay
    # holds the record just after it until the replaying daemon has begun that step too, so each
    # step starts at the same sample as on the line (station/replay/director.py).
    step_start_t: dict[int, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def restart_index(self) -> int | None:
        """Index of the first sample after the recorded program stop (None: no stop recorded, or
        the record ends there)."""
        if self.restart_after_t is None:
            return None
        k = int(np.searchsorted(self.time_s, float(self.restart_after_t), side="right"))
        return k if 0 < k < len(self) else None

    def step_start_indices(self) -> list[tuple[int, int]]:
        """(step, index of the first sample after the recorded start of that step), in step order;
        steps whose start is outside the record are left out."""
        out = []
        for k in sorted(self.step_start_t):
            i = int(np.searchsorted(self.time_s, float(self.step_start_t[k]), side="right"))
            if 0 < i < len(self):
                out.append((int(k), i))
        return out

    def seq_index(self) -> np.ndarray:
        """Frame sequence number of every sample: gaps in the clock longer than 1.5 sample periods
        are samples the link lost, so the replay board skips as many sequence numbers (the
        station then counts them lost, as it did when the data were recorded). The gap where the
        station stopped the board to program it is no loss: the board measured nothing then."""
        n = len(self)
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        dt = np.diff(self.time_s) * self.identity.odr_hz
        gaps = np.where(dt > 1.5, np.rint(dt) - 1, 0).astype(np.int64)
        k = self.restart_index()
        if k is not None:
            gaps[k - 1] = 0
        return np.concatenate([[0], np.cumsum(gaps + 1)])


def answer_index(position: np.ndarray | None, start: int, wanted: int) -> int | None:
    """Where a recorded operator's answer to "turn the plate to `wanted`" took effect: the first
    recorded sample at or after `start` that the station stored at that position (while a prompt
    waits the station stores -1, unknown). None: the recording never reached it (the recorded
    batch ended at that prompt, or the record is over)."""
    if position is None:
        return None
    hit = np.flatnonzero(np.asarray(position[start:]) == int(wanted))
    return int(start + hit[0]) if len(hit) else None


@dataclass
class Recording:
    """A batch to replay: its DUTs, the profile it ran and where it came from."""

    source: str  # e.g. "batch 12 of line-A (sqlite:///var/station.db)" or "3 CSV logs"
    profile: str
    duts: list[RecordedDut]
    config_snapshot: dict[str, Any] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)  # DUTs that cannot be replayed, with the reason
    before_label: str = "recorded"
    batch_state: str = "finished"  # how the recorded batch ended (logs: expected to finish)
    batch_error: str = ""  # why, if it did not finish ("aborted by Ana at ...", "safety trip: ...")
    source_note: str = ""  # how the source was read, e.g. through a migrated copy of an older schema

    def only(self, serials: list[str] | None) -> "Recording":
        """Keep the DUTs whose serial (or slot) is listed; unknown names are an error."""
        if not serials:
            return self
        known = {d.serial for d in self.duts} | {d.slot for d in self.duts}
        unknown = [s for s in serials if s not in known]
        if unknown:
            raise StationError(f"--only: {', '.join(unknown)} not in the recording "
                               f"(it has {', '.join(d.serial for d in self.duts)})")
        keep = [d for d in self.duts if d.serial in serials or d.slot in serials]
        return dataclasses.replace(self, duts=keep)


# ---- counts ---------------------------------------------------------------------------------
def to_counts(identity: Identity, acc_g: np.ndarray, temp_c: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """g and C back to the board's counts. The stored values are counts x LSB at 1e-7 g / 1e-4 C,
    so rounding recovers the counts exactly; a value off its LSB grid is refused (it was not
    recorded by a board with this identity, and replaying it would change the data)."""
    lsb_g = identity.ug_per_lsb / 1e6
    acc = np.rint(np.asarray(acc_g, dtype=np.float64) / lsb_g)
    tc = np.rint((np.asarray(temp_c, dtype=np.float64) - T_REF_C) * identity.t_lsb_per_c + identity.t_lsb_at_25c)
    if len(acc):
        err_g = float(np.max(np.abs(acc * lsb_g - acc_g)))
        err_c = float(np.max(np.abs(identity.temp_c(tc) - temp_c)))
        if err_g > 0.51e-7 + 1e-12 or err_c > 0.51e-4 + 1e-12:
            raise StationError(f"{what}: the samples are not on the board's LSB grid "
                               f"({err_g * 1e6:.3g} ug, {err_c * 1e3:.3g} mC off): cannot replay them as counts")
        if np.max(np.abs(acc)) > COUNT_LIMIT or np.max(np.abs(tc)) > COUNT_LIMIT:
            raise StationError(f"{what}: counts beyond int32")
    return acc.astype(np.int64), tc.astype(np.int64)
