"""The calibration part of a simulated board's firmware, shared by serial and CAN boards.

Non-volatile memory (`BoardNvm`) holds the thermal coefficients (design 3.1 $CALW / 3.2
CAL_FIELD+CAL_COMMIT), the SFEM (serial boards only) and the compensation switch; it survives a
simulated power-cycle (the boards' `power_cycle()` clears only their RAM state). A virgin board
reads back zeros with compensation off. With compensation on, the board turns the counts it would
send into compensated counts: martinez2022 eq. 13 with its OWN temperature reading, then the SFEM
`A (acc - b)` if one is stored, then back to counts.

Fault injection for the write path (what the station's program-and-verify must catch):
  flip_next_write(n, field, bit)  a bit of one value flips on the way (the frame checksum passed,
                                  the stored value differs: only the CRC can tell)
  refuse_writes(n)                the next n writes are refused (flash write failed)
  drop_replies(n)                 the next n calibration replies are lost (the command still acts)
  corrupt_readback_crc(n)         the next n read-backs report a wrong CRC beside the right values
                                  (a board whose stored CRC word is damaged: only the CRC compare
                                  of the read-back can tell)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from drivers.protocol.cal_record import N_SFEM, N_THERMAL, crc32_f32, to_f32
from contracts.types import T_REF_C

ZERO_THERMAL = (0.0,) * N_THERMAL


@dataclass
class BoardNvm:
    """What the board's flash keeps across power-cycles."""

    thermal: tuple[float, ...] = ZERO_THERMAL  # tdb x y z mg/C, tdsf x y z ppm/C (float32)
    sfem: tuple[float, ...] | None = None  # a11..a33, b x y z (g) (float32)
    comp: bool = False
    writes: int = 0  # flash write cycles (tests read it)

    @property
    def thermal_crc(self) -> int:
        return crc32_f32(self.thermal)

    @property
    def sfem_crc(self) -> int:
        return crc32_f32(self.sfem if self.sfem is not None else ())


def flip_bit(value: float, bit: int) -> float:
    """The float32 value with one bit of its IEEE representation flipped."""
    (u,) = struct.unpack("<I", struct.pack("<f", value))
    return struct.unpack("<f", struct.pack("<I", u ^ (1 << int(bit))))[0]


@dataclass
class CalFirmware:
    """Calibration firmware state: NVM plus the write-path faults armed by tests."""

    nvm: BoardNvm = field(default_factory=BoardNvm)
    flip: list[tuple[int, int]] = field(default_factory=list)  # pending flips: (field, bit)
    refuse: int = 0
    drop: int = 0
    bad_crc: int = 0
    flips_done: int = 0
    refused_done: int = 0
    dropped_done: int = 0
    bad_crcs_done: int = 0

    # ---- faults ------------------------------------------------------------------------------
    def flip_next_write(self, n: int = 1, field_index: int = 0, bit: int = 3) -> None:
        self.flip += [(int(field_index), int(bit))] * int(n)

    def refuse_writes(self, n: int = 1) -> None:
        self.refuse += int(n)

    def drop_replies(self, n: int = 1) -> None:
        self.drop += int(n)

    def take_drop(self) -> bool:
        """True if the reply about to be sent is lost."""
        if self.drop > 0:
            self.drop -= 1
            self.dropped_done += 1
            return True
        return False

    def corrupt_readback_crc(self, n: int = 1) -> None:
        self.bad_crc += int(n)

    def readback_crc(self) -> int:
        """The thermal CRC a read-back reports (a pending corruption applied)."""
        if self.bad_crc > 0:
            self.bad_crc -= 1
            self.bad_crcs_done += 1
            return self.nvm.thermal_crc ^ 0x00010000
        return self.nvm.thermal_crc

    def take_refuse(self) -> bool:
        if self.refuse > 0:
            self.refuse -= 1
            self.refused_done += 1
            return True
        return False

    def on_the_way(self, values) -> tuple[float, ...]:
        """Values as they arrive in the board's RAM (a pending flip applied)."""
        vals = list(to_f32(values))
        if self.flip:
            k, bit = self.flip.pop(0)
            vals[k % len(vals)] = flip_bit(vals[k % len(vals)], bit)
            self.flips_done += 1
        return tuple(vals)

    # ---- storing -----------------------------------------------------------------------------
    def store_thermal(self, values) -> None:
        vals = to_f32(values)
        assert len(vals) == N_THERMAL
        self.nvm.thermal = vals
        self.nvm.writes += 1

    def store_sfem(self, values) -> None:
        vals = to_f32(values)
        assert len(vals) == N_SFEM
        self.nvm.sfem = vals
        self.nvm.writes += 1

    # ---- compensation ------------------------------------------------------------------------
    def compensate_g(self, acc_g: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Eq. 13 per axis with the board's temperature, then the SFEM if stored. (n,3) g."""
        th = np.asarray(self.nvm.thermal, dtype=np.float64)
        tdb_g, tdsf = th[:3] * 1e-3, th[3:] * 1e-6
        dt = (np.asarray(temp_c, dtype=np.float64) - T_REF_C)[:, None]
        out = (np.asarray(acc_g, dtype=np.float64) - tdb_g * dt) / (1.0 + tdsf * dt)
        if self.nvm.sfem is not None:
            s = np.asarray(self.nvm.sfem, dtype=np.float64)
            a, b = s[:9].reshape(3, 3), s[9:]
            out = (out - b) @ a.T
        return out

    def compensate_counts(self, acc_counts: np.ndarray, temp_c: np.ndarray, ug_per_lsb: float) -> np.ndarray:
        """Compensated counts (int64) from raw counts; the board's output when compensation is on."""
        lsb_g = ug_per_lsb * 1e-6
        out = self.compensate_g(np.asarray(acc_counts, dtype=np.float64) * lsb_g, temp_c)
        return np.rint(out / lsb_g).astype(np.int64)
