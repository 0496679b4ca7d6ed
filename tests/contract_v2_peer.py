"""A board written from docs/design.md 3.1 alone, on a real pseudo-terminal (issue 42).

Why here and not drivers/sim: the station's codec (drivers/protocol/serial_frames.py) and this
peer must not share a reading of the contract, or a misreading shared by both passes every test
that pairs them. So this file imports nothing of the station: its own `$BODY*HH` framing and XOR,
its own float32 rounding (struct), its own CRC-32 (zlib of struct-packed float32 little-endian in
contract order), its own float text (Python's repr of the float32 value: a different text than the
board's shortest positional one, which the station must read all the same).

It speaks: ID (with optional trailing key=value fields), START / STOP, SCAL / SCRR (a result or an
E,SCRR set by the test), SFTW / SFTC / SFTR (the version-2 record), and sends whatever the test
pushes unsolicited (`send`: E,SENSOR, G, D frames). Faults a test arms: `wrong_crc` (A,SFTC with a
CRC off by one bit, nothing stored), `drop_acks` (the next n SFTW/SFTC acks are lost),
`stored_flip` (the stored record's first coefficient differs from what was staged, so a read-back
disagrees with its own CRC), `refuse_commit` (E,SFTC).
"""

from __future__ import annotations

import asyncio
import math
import os
import struct
import tty
import zlib
from functools import reduce
from operator import xor


def frame(body: str) -> bytes:
    raw = body.encode("ascii")
    return b"$%s*%02X\n" % (raw, reduce(xor, raw, 0))


def parse(line: bytes) -> list[str] | None:
    line = line.rstrip(b"\r")
    if not line.startswith(b"$") or len(line) < 4 or line[-3:-2] != b"*":
        return None
    body = line[1:-3]
    try:
        if reduce(xor, body, 0) != int(line[-2:], 16):
            return None
    except ValueError:
        return None
    return body.decode("ascii").split(",")


def f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def crc_of(values: list[float]) -> int:
    return zlib.crc32(struct.pack(f"<{len(values)}f", *values)) & 0xFFFFFFFF


class ContractPeer:
    """The device end of a pty (the station opens `path` like a USB CDC port)."""

    def __init__(self, ident: str = "I,CP0001,ADXL355,cp-1,3.9,-9.05,1885,3.125", extras: str = "") -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self._slave)
        self.ident = ident
        self.extras = extras  # ",reset=power,boots=1,..." appended to the I frame
        self.commands: list[list[str]] = []
        self._rx = b""
        self.staged: dict[int, list[float]] = {}
        self.stored: tuple[list[float], int] | None = None  # (51 values, crc)
        self.selfcal_on = False
        self.scrr_reply = "E,SCRR,no result: no segments"
        self.wrong_crc = 0
        self.drop_acks = 0
        self.stored_flip = False
        self.refuse_commit = 0
        self.before_next_reply = b""  # sent (once) just before the next reply: an unsolicited frame in flight
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.master, self._on_readable)

    def close(self) -> None:
        self._loop.remove_reader(self.master)
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def send(self, raw: bytes) -> None:
        view = memoryview(raw)
        while view:
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                n = 0
            view = view[n:]

    def _on_readable(self) -> None:
        try:
            data = os.read(self.master, 65536)
        except (BlockingIOError, OSError):
            return
        self._rx += data
        while b"\n" in self._rx:
            line, self._rx = self._rx.split(b"\n", 1)
            fields = parse(line)
            if fields is not None:
                self.commands.append(fields)
                self._command(fields)

    def _ack(self, body: str) -> None:
        if self.drop_acks:
            self.drop_acks -= 1
            return
        self.send(frame(body))

    def _command(self, f: list[str]) -> None:
        cmd = f[0]
        if self.before_next_reply:
            self.send(self.before_next_reply)
            self.before_next_reply = b""
        if cmd == "ID":
            self.send(frame(self.ident + self.extras))
        elif cmd in ("START", "STOP"):
            self.send(frame(f"A,{cmd}"))
        elif cmd == "SCAL" and len(f) == 2 and f[1] in ("0", "1"):
            self.selfcal_on = f[1] == "1"
            self.send(frame("A,SCAL"))
        elif cmd == "SCRR":
            self.send(frame(self.scrr_reply))
        elif cmd == "SFTW":
            self._sftw(f)
        elif cmd == "SFTC":
            self._sftc(f)
        elif cmd == "SFTR":
            self._sftr(f)
        else:
            self.send(frame(f"E,{cmd},unknown command"))

    def _sftw(self, f: list[str]) -> None:
        if len(f) != 14 or f[1] not in ("0", "1", "2", "3"):
            self.send(frame("E,SFTW,need a power 0..3 and 12 values"))
            return
        try:
            vals = [f32(float(x)) for x in f[2:]]
        except ValueError:
            self.send(frame("E,SFTW,bad number"))
            return
        self.staged[int(f[1])] = vals
        self._ack(f"A,SFTW,{f[1]}")

    def _sftc(self, f: list[str]) -> None:
        if self.refuse_commit:
            self.refuse_commit -= 1
            self.send(frame("E,SFTC,flash write failed"))
            return
        if len(f) != 5 or sorted(self.staged) != [0, 1, 2, 3]:
            self.staged.clear()
            self.send(frame("E,SFTC,not all four powers staged"))
            return
        head = [f32(float(x)) for x in f[1:4]]
        values = head + [v for k in range(4) for v in self.staged[k]]
        self.staged.clear()
        if not all(math.isfinite(v) for v in values) or not head[1] < head[2]:
            self.send(frame("E,SFTC,non-finite value or t_lo >= t_hi"))
            return
        crc = crc_of(values)
        if crc != int(f[4], 16):
            self.send(frame("E,SFTC,CRC mismatch"))
            return
        if self.wrong_crc:
            self.wrong_crc -= 1
            self._ack(f"A,SFTC,{crc ^ 1:08X}")
            return
        if self.stored_flip:
            values = values[:3] + [f32(values[3] + 0.5)] + values[4:]
        self.stored = (values, crc)
        self._ack(f"A,SFTC,{crc:08X}")

    def _sftr(self, f: list[str]) -> None:
        if self.stored is None:
            self.send(frame("E,SFTR,no cubic SFEM stored"))
            return
        values, crc = self.stored
        if f[1:] == ["H"]:
            self.send(frame("T,H," + ",".join(repr(v) for v in values[:3]) + f",{crc:08X}"))
        elif len(f) == 2 and f[1] in ("0", "1", "2", "3"):
            k = int(f[1])
            self.send(frame(f"T,{k}," + ",".join(repr(v) for v in values[3 + 12 * k: 15 + 12 * k])))
        else:
            self.send(frame("E,SFTR,bad part"))
