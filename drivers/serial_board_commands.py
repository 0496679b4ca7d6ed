"""The serial board's commands beyond streaming (design 3.1): calibration write-back and read-back,
the board's own calibrator ($SCAL / $SCRR / G) and the version-2 record ($SFTW / $SFTC / $SFTR,
docs/design.md 3.1). Kept apart from drivers/serial_board.py (the link, the frames, the
sample stream) so that each stays one responsibility: `SerialBoard` inherits these, and every one
of them is one request and its reply on the link that class runs.
"""

from __future__ import annotations

import asyncio
from typing import Any

from contracts.board_health import CAP_SELFCAL, CAP_SFEM_CUBIC
from contracts.sfem_cubic import N_POWERS, SfemCubicRecord
from drivers.base import BoardDriver, BoardSelfCalResult, CalibrationError, CalReadback, DriverError
from drivers.protocol import serial_frames as sf
from drivers.protocol.selfcal_frames import SegmentReportFrame, SelfCalResultFrame


class BoardErrorReply(DriverError):
    """The board answered a command with `E,<code>,<text>`."""

    def __init__(self, port: str, code: str, text: str) -> None:
        super().__init__(f"board {port} error {code}: {text}")
        self.code, self.text = code, text


def reply_key(frame: sf.Frame) -> str:
    """Which waiting command a reply frame answers: an ack its command's name, a read its frame type
    (`C` CALR, `S` SFER, `R` SCRR, `TH` / `T0`..`T3` SFTR)."""
    if isinstance(frame, sf.AckFrame):
        return frame.command
    if isinstance(frame, sf.CalReadFrame):
        return "C"
    if isinstance(frame, sf.SfemReadFrame):
        return "S"
    if isinstance(frame, SelfCalResultFrame):
        return "R"
    if isinstance(frame, sf.SfemCubicHeadFrame):
        return "TH"
    if isinstance(frame, sf.SfemCubicRowFrame):
        return f"T{frame.power}"
    raise TypeError(f"not a reply: {frame!r}")


class SerialBoardCommands(BoardDriver):
    """Request / reply commands of a serial board; the link (`_write`, `_check`, the waiters) is
    drivers/serial_board.SerialBoard's."""

    port: str
    ack_timeout_s: float
    _loop: asyncio.AbstractEventLoop | None
    _cmd_lock: asyncio.Lock
    _ack_waiters: dict[str, asyncio.Future[Any]]
    _error: DriverError | None
    _segments: list[SegmentReportFrame]

    def _check(self) -> None:
        raise NotImplementedError

    def _write(self, raw: bytes) -> None:
        raise NotImplementedError

    def _drain(self) -> None:
        raise NotImplementedError

    async def _command(self, raw: bytes, key: str) -> None:
        raise NotImplementedError

    # ---- calibration write-back (one attempt each; BoardDriver.program_thermal retries) ------
    @staticmethod
    def _ack_crc(frame: sf.AckFrame, what: str) -> int:
        try:
            return int(frame.args[0], 16)
        except (IndexError, ValueError):
            raise CalibrationError("crc_mismatch", f"{what} acknowledged without a CRC: {frame.args!r}") from None

    async def write_thermal(self, tdb_mg_per_c, tdsf_ppm_per_c) -> int:
        ack = await self._cal_request(sf.cmd_calw(tdb_mg_per_c, tdsf_ppm_per_c), "CALW", "CALW")
        return self._ack_crc(ack, "CALW")

    async def read_thermal(self) -> CalReadback:
        c = await self._cal_request(sf.cmd_calr(), "C", "CALR")
        return CalReadback(tuple(c.values), c.crc, c.comp, c.record)

    async def set_compensation(self, on: bool) -> None:
        await self._cal_request(sf.cmd_comp(on), "COMP", "COMP")

    async def write_sfem(self, a_3x3, b_g) -> int:
        ack = await self._cal_request(sf.cmd_sfew(a_3x3, b_g), "SFEW", "SFEW")
        return self._ack_crc(ack, "SFEW")

    async def read_sfem(self) -> CalReadback:
        s = await self._cal_request(sf.cmd_sfer(), "S", "SFER")
        return CalReadback(tuple(s.values), s.crc, False)

    # ---- issue 42: the on-board calibrator and the version-2 record (docs/design.md 3.1)
    @property
    def supports_selfcal(self) -> bool:
        return self._has_cap(CAP_SELFCAL)

    @property
    def supports_sfem_cubic(self) -> bool:
        return self._has_cap(CAP_SFEM_CUBIC)

    async def _request(self, raw: bytes, key: str, what: str):
        """Send one command and wait for its reply frame (`reply_key` == key); one attempt.
        Raises BoardErrorReply on an `E` reply, DriverError when none comes within ack_timeout_s."""
        self._check()
        assert self._loop is not None
        async with self._cmd_lock:
            fut = self._loop.create_future()
            self._ack_waiters[key] = fut
            try:
                self._write(raw)
                return await asyncio.wait_for(asyncio.shield(fut), self.ack_timeout_s)
            except asyncio.TimeoutError:
                self._check()
                raise DriverError(f"no reply to {what} from {self.port} within {self.ack_timeout_s:g} s") from None
            finally:
                self._ack_waiters.pop(key, None)

    async def set_selfcal(self, on: bool) -> None:
        """`$SCAL,<0|1>` -> `A,SCAL` (re-sent like every command: switching it twice is harmless)."""
        await self._command(sf.cmd_scal(on), "SCAL")

    async def read_selfcal(self) -> BoardSelfCalResult:
        """`$SCRR` -> `R,...`; the board's `E,SCRR,<text>` (no result yet) raises BoardErrorReply."""
        r = await self._request(sf.cmd_scrr(), "R", "SCRR")
        return BoardSelfCalResult(r.tdb_mg_per_c, r.tdsf_ppm_per_c, r.n_segments,
                                  (bool(r.flags & 1), bool(r.flags & 2), bool(r.flags & 4)))

    def take_selfcal_segments(self) -> list[SegmentReportFrame]:
        self._drain()
        out, self._segments = self._segments, []
        return out

    async def _cal_request(self, raw: bytes, key: str, what: str):
        """`_request` for the calibration record: every failure a CalibrationError of its kind (a
        link that is gone stays a DriverError)."""
        self._check()
        try:
            return await self._request(raw, key, what)
        except BoardErrorReply as exc:
            raise CalibrationError("refused", f"{what} refused by {self.port}: {exc.code} {exc.text}") from None
        except DriverError as exc:
            if self._error is not None:
                raise
            raise CalibrationError("no_reply", str(exc)) from None

    async def write_sfem_cubic(self, rec: SfemCubicRecord) -> int:
        """Store a cubic SFEM (version-2 record); returns the board's CRC. ONE attempt, as every
        calibration primitive here (the caller's policy retries, cf. BoardDriver.program_thermal):
        the four SFTW, each acknowledged with its own power, then SFTC, whose `A,SFTC,<crc>` must
        carry the station's CRC of the float32 record; else CalibrationError: "no_reply", "refused"
        (an `E` reply, or an ack for another power), "crc_mismatch". ValueError, before anything is
        sent, for a record float32 cannot hold."""
        rec = rec.to_f32()
        frames = sf.sfem_cubic_commands(rec)
        for k, raw in enumerate(frames[:N_POWERS]):
            ack = await self._cal_request(raw, "SFTW", f"SFTW,{k}")
            if ack.args[:1] != (str(k),):
                raise CalibrationError("refused", f"SFTW,{k} acknowledged as SFTW {','.join(ack.args)} by {self.port}")
        ack = await self._cal_request(frames[N_POWERS], "SFTC", "SFTC")
        board_crc = self._ack_crc(ack, "SFTC")
        want = rec.crc32()
        if board_crc != want:
            raise CalibrationError("crc_mismatch", f"{self.port} stored the cubic SFEM with CRC {board_crc:08X}, "
                                   f"station computed {want:08X}")
        return board_crc

    async def read_sfem_cubic(self) -> SfemCubicRecord:
        """`$SFTR,H` and `$SFTR,0..3` -> the stored record. CalibrationError "refused" when the board
        has none (`E,SFTR`), "readback_mismatch" when the values it sent are not the record its CRC
        names (or not a valid record at all)."""
        head = await self._cal_request(sf.cmd_sftr("H"), "TH", "SFTR,H")
        rows = []
        for k in range(N_POWERS):
            row = await self._cal_request(sf.cmd_sftr(k), f"T{k}", f"SFTR,{k}")
            rows.append(row.values)
        try:
            rec = SfemCubicRecord(head.t_ref_c, head.t_lo_c, head.t_hi_c, tuple(rows))
        except ValueError as exc:
            raise CalibrationError("readback_mismatch", f"{self.port} sent a cubic SFEM that is not one: {exc}") from None
        if rec.crc32() != head.crc:
            raise CalibrationError("readback_mismatch", f"{self.port}: the cubic SFEM read back has CRC "
                                   f"{rec.crc32():08X}, the board names {head.crc:08X}")
        return rec

