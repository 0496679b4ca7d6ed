"""Instrument interfaces: one per kind of instrument, in the spirit of OpenHTF plugs.

Real drivers (serial, CAN, Modbus TCP/RTU) implement these. Simulated hardware does not get its
own implementation of these interfaces: it sits on the far side of a real link (pseudo-terminal,
slcan adapter on a pseudo-terminal, pymodbus server on 127.0.0.1), so the very same drivers run
against it. Drivers turn bytes into SampleBlocks and commands into bytes; they know nothing of
calibration.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

from contracts.board_health import BoardRecordInfo
from contracts.sfem_cubic import SfemCubicRecord
from contracts.types import Identity, SampleBlock
from drivers.protocol.selfcal_frames import SegmentReportFrame


class DriverError(Exception):
    """A link failed (port vanished, device unreachable, no reply). Faults one slot or device."""


class NotSupportedByBoard(DriverError):
    """The board (or its kind of link) cannot do what was asked: no on-board calibrator, no
    version-2 record. A caller checks the capability property first (`supports_selfcal`,
    `supports_sfem_cubic`); this is what it gets when it did not."""


CAL_ERROR_KINDS = ("crc_mismatch", "refused", "no_reply", "readback_mismatch", "comp_not_set", "unsupported")


class CalibrationError(DriverError):
    """Writing or reading a board's calibration failed after the retry policy (design 4, program
    and verify). `kind` names what went wrong (CAL_ERROR_KINDS); the sequencer faults that slot
    with the message. Never a silent pass: every path that cannot prove the stored values equal
    the written ones raises this."""

    def __init__(self, kind: str, message: str, attempts: int = 1) -> None:
        assert kind in CAL_ERROR_KINDS, kind
        super().__init__(message)
        self.kind = kind
        self.attempts = attempts


@dataclass(frozen=True)
class CalReadback:
    """What a board says it stores: values as float32, their CRC-32 and the compensation switch."""

    values: tuple[float, ...]
    crc: int
    comp: bool
    record: BoardRecordInfo | None = None  # the `rec_*` keys of a `C` reply (version-2 firmware)


@dataclass(frozen=True)
class BoardSelfCalResult:
    """The board's own streaming calibrator's result (`$SCRR` -> `R`, design 3.1): per axis x y z
    the TDB in mg/C and the TDSF in ppm/C, how many segments it used, and which axes' TDSF came out
    positive and were clamped to 0 (flags bit k)."""

    tdb_mg_per_c: tuple[float, float, float]
    tdsf_ppm_per_c: tuple[float, float, float]
    n_segments: int
    clamped_axes: tuple[bool, bool, bool]


@dataclass
class ProgramReport:
    """Outcome of write + read back + compensation on for one board (program_thermal)."""

    crc: int  # CRC-32 of the written float32 values (station side == board side when ok)
    readback: CalReadback
    comp: bool
    attempts: int  # write attempts used (1 = first try)
    retries: list[str] = field(default_factory=list)  # why each failed attempt failed
    # Board time (s, the driver's sample clock) of the latest sample received when compensation was
    # confirmed on: every later sample is compensated (replies and samples share one ordered link).
    comp_from_t: float | None = None

    def to_json(self) -> dict:
        return {
            "crc": f"{self.crc:08X}",
            "readback_crc": f"{self.readback.crc:08X}",
            "readback_values": list(self.readback.values),
            "readback_identical": self.readback.crc == self.crc,
            "comp": self.comp,
            "attempts": self.attempts,
            "retries": list(self.retries),
            "comp_from_t": self.comp_from_t,
        }


@dataclass
class LinkStats:
    """Counters every board link keeps; corrupt input is counted and skipped, never fatal."""

    frames_ok: int = 0
    frames_bad_checksum: int = 0
    frames_malformed: int = 0  # short line, unknown type, unparsable field
    bytes_skipped: int = 0  # garbage between frames
    samples_lost: int = 0  # sequence gaps, and samples dropped from a full queue (samples_lost_queue)
    samples_lost_queue: int = 0  # of samples_lost: dropped by this driver, its queue full (nobody read)
    # of samples_lost: lost while the station ran behind this link (its backlog, not the board's
    # doing; station/daemon/intake_monitor.py), queue drops included; set by the station's pump
    samples_lost_station: int = 0
    errors_reported: int = 0  # `E,...` frames from the board
    resets: int = 0  # the board restarted while streaming (its seq went back): StreamBreak "reset"
    clock_jumps: int = 0  # its clock jumped while its seq ran on: StreamBreak "clock_jump"
    frames_after_break: int = 0  # sample frames of another timeline (from the one that confirmed a break to the next START): not taken
    # the board restarted between two identity replies (its `boots` moved, docs/design.md 3.1)
    board_restarts: int = 0
    sensor_reinits_reported: int = 0  # of errors_reported: `E,SENSOR,...` (the board re-initialised its sensor)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class StreamBreak:
    """A stream that is no longer one timeline of one board (design 3.1): the board restarted
    while streaming (`reset`: its seq went back, its clock with it) or its clock jumped while its
    seq ran on (`clock_jump`). The station cannot join two timelines into one run: the samples
    after a break are not delivered, and the DUT's run ends with `reason`."""

    kind: str  # "reset" | "clock_jump"
    at_t_s: float | None  # board time of the last sample before the break (None: none yet)
    reason: str  # in words, for the operator and the record


class BoardDriver(abc.ABC):
    """One DUT board. All methods are coroutines that never block the event loop."""

    stats: LinkStats
    identity: Identity | None = None  # the latest identity reply (drivers set it in identify())
    # the latest unsolicited `E,SENSOR,...` / `E,NVM,...` the board sent, as "SENSOR: <text>": what
    # the board said of its own trouble, for the run's notes (None: nothing said)
    last_board_error: str | None = None

    @abc.abstractmethod
    async def open(self) -> None: ...

    @abc.abstractmethod
    async def identify(self, timeout_s: float = 2.0) -> Identity: ...

    @abc.abstractmethod
    async def start(self) -> None: ...

    @abc.abstractmethod
    async def stop(self) -> None: ...

    def backlog_samples(self) -> int:
        """Samples received by this host and not handed out yet, as far as the driver can see (the
        port's OS buffer, bytes not parsed, its queue): how far behind its board the station runs
        (station/daemon/intake_monitor.py). 0 when it cannot tell."""
        return 0

    def take_breaks(self) -> list[StreamBreak]:
        """Stream breaks seen since the last call (the pump asks after every block). A link whose
        frames carry no board clock (CAN, design 3.2: time is our own sample count) reports none:
        a reset there shows as lost samples only."""
        return []

    def discard_held(self) -> int:
        """Drop samples received but not yet read (returns how many): called before a NEW run
        starts streaming, since samples that arrived after the previous run's last read (until its
        STOP took effect) are not the new run's. A driver that holds none need not override it."""
        return 0

    @abc.abstractmethod
    async def set_odr(self, odr_hz: float) -> None: ...

    @abc.abstractmethod
    async def read_block(self, timeout_s: float = 1.0) -> SampleBlock:
        """Samples received since the last call (possibly empty after timeout_s).

        Raises DriverError when the link is gone (port closed, bus down).
        """

    @abc.abstractmethod
    async def close(self) -> None: ...

    # ---- calibration write-back (design 3.1/3.2, program and verify) ----------------------
    # Boards that can store coefficients override the four primitives; each primitive makes ONE
    # attempt and raises CalibrationError (kind) on a refused write, a CRC mismatch or no reply.
    # program_thermal() is the retry policy around them.
    cal_retries: int = 3
    last_sample_t: float | None = None  # board time of the latest sample received (drivers set it)
    last_rx_wall: float = 0.0  # time.monotonic() of the latest frame received on this board's link

    async def write_thermal(self, tdb_mg_per_c, tdsf_ppm_per_c) -> int:
        """Store the six thermal coefficients; returns the CRC the board reports for what it stored."""
        raise CalibrationError("unsupported", f"{self!r} cannot store calibration coefficients")

    async def read_thermal(self) -> CalReadback:
        raise CalibrationError("unsupported", f"{self!r} cannot read calibration coefficients")

    async def set_compensation(self, on: bool) -> None:
        raise CalibrationError("unsupported", f"{self!r} has no on-board compensation")

    async def write_sfem(self, a_3x3, b_g) -> int:
        raise CalibrationError("unsupported", f"{self!r} cannot store an SFEM")

    async def read_sfem(self) -> CalReadback:
        raise CalibrationError("unsupported", f"{self!r} cannot read an SFEM")

    # ---- issue 42: the board's own calibrator and the version-2 record (docs/design.md 3.1)
    # A board says what it can in its identity (`caps=`); a link or board without it keeps these
    # defaults: the capability is False and the methods raise NotSupportedByBoard (a DriverError).
    def _unsupported(self, what: str) -> NotSupportedByBoard:
        return NotSupportedByBoard(f"{self!r}: {what} is not supported by this board")

    def _has_cap(self, cap: str) -> bool:
        return self.identity is not None and cap in self.identity.caps

    @property
    def supports_selfcal(self) -> bool:
        """The board runs martinez2022 3.3 itself (`caps` holds "scal"): set_selfcal / read_selfcal work."""
        return False

    async def set_selfcal(self, on: bool) -> None:
        """The on-board streaming calibrator off / on (on restarts it)."""
        raise self._unsupported("the on-board calibrator ($SCAL)")

    async def read_selfcal(self) -> BoardSelfCalResult:
        """The on-board calibrator's result now."""
        raise self._unsupported("the on-board calibrator's result ($SCRR)")

    def take_selfcal_segments(self) -> list[SegmentReportFrame]:
        """The segments the on-board calibrator reported (`G` frames) since the last call; a board
        without a calibrator reports none."""
        return []

    @property
    def supports_sfem_cubic(self) -> bool:
        """The board stores and applies a version-2 record, the cubic thermal SFEM (`caps` holds "sfem3")."""
        return False

    async def write_sfem_cubic(self, rec: SfemCubicRecord) -> int:
        """Store a cubic SFEM; returns the CRC the board reports (equal to rec.crc32(), else
        CalibrationError). One attempt, like the primitives above: the caller retries."""
        raise CalibrationError("unsupported", f"{self!r}: the cubic SFEM ($SFTW) is not supported by this board")

    async def read_sfem_cubic(self) -> SfemCubicRecord:
        """The cubic SFEM the board stores (CalibrationError when none)."""
        raise CalibrationError("unsupported", f"{self!r}: the cubic SFEM ($SFTR) is not supported by this board")

    async def _retried(self, step, retries: list[str], label: str, failed: str):
        """Run step() up to cal_retries times: a CalibrationError other than "unsupported" is
        noted in `retries` and retried; the last one is raised when the attempts are used up.
        Returns (step's result, the attempt that succeeded)."""
        last: CalibrationError | None = None
        for attempt in range(1, self.cal_retries + 1):
            try:
                return await step(), attempt
            except CalibrationError as exc:
                if exc.kind == "unsupported":
                    raise
                last = exc
                retries.append(f"{label}attempt {attempt}: {exc.kind}: {exc}")
        assert last is not None
        raise CalibrationError(last.kind, f"{failed} after {self.cal_retries} attempts: {last}",
                               attempts=self.cal_retries)

    async def program_thermal(self, tdb_mg_per_c, tdsf_ppm_per_c, *, compensation: bool = True) -> ProgramReport:
        """Write, read back and compare (CRC and every value), then switch compensation on and
        confirm it. Up to `cal_retries` write attempts; a CRC mismatch, a refused write, a
        missing reply or a read-back that differs is retried, and raised as CalibrationError
        (the last kind) when the attempts are used up."""
        from drivers.protocol.cal_record import crc32_f32, to_f32

        want = to_f32([*tdb_mg_per_c, *tdsf_ppm_per_c])
        want_crc = crc32_f32(want)
        retries: list[str] = []

        async def write_and_read_back() -> CalReadback:
            board_crc = await self.write_thermal(want[:3], want[3:])
            if board_crc != want_crc:
                raise CalibrationError("crc_mismatch", f"board stored CRC {board_crc:08X}, station computed {want_crc:08X}")
            rb = await self.read_thermal()
            if rb.crc != want_crc or tuple(rb.values) != want:
                raise CalibrationError("readback_mismatch", f"read back CRC {rb.crc:08X} values {list(rb.values)}, "
                                       f"written CRC {want_crc:08X}")
            return rb

        async def switch_compensation_on() -> CalReadback:
            await self.set_compensation(True)
            rb = await self.read_thermal()
            if rb.comp and rb.crc == want_crc:
                return rb
            raise CalibrationError("comp_not_set", "compensation still off after COMP 1")

        rb, attempt = await self._retried(write_and_read_back, retries, "", "calibration write failed")
        comp = rb.comp
        if compensation:
            rb, _ = await self._retried(switch_compensation_on, retries, "compensation ",
                                        "compensation could not be switched on")
            comp = True
        return ProgramReport(crc=want_crc, readback=rb, comp=comp, attempts=attempt, retries=retries,
                             comp_from_t=self.last_sample_t)


class LampRelay(abc.ABC):
    @abc.abstractmethod
    async def set_lamp(self, on: bool) -> None: ...

    @abc.abstractmethod
    async def read_lamp(self) -> bool: ...

    async def set_watchdog(self, seconds: int) -> None:
        """Arm the relay's host watchdog (design 3.3): with no request for `seconds`, the relay
        switches the lamp off by itself (0 = off). A relay without one raises DriverError."""
        raise DriverError(f"{type(self).__name__} has no host watchdog")


class Fixture(abc.ABC):
    @abc.abstractmethod
    async def move_to(self, position: int) -> None: ...

    @abc.abstractmethod
    async def position(self) -> int: ...

    @abc.abstractmethod
    async def moving(self) -> bool: ...


class Thermometer(abc.ABC):
    @abc.abstractmethod
    async def read_temp_c(self) -> float: ...


class Chamber(abc.ABC):
    @abc.abstractmethod
    async def set_setpoint_c(self, setpoint_c: float) -> None: ...

    @abc.abstractmethod
    async def read_temp_c(self) -> float: ...
