"""Driver-level fuzz (issue 10): hostile bytes on the real links, the real drivers reading.

Serial: bytes are written into the master side of a real pty while `SerialBoard` reads the slave
side from the event loop, as on a station. CAN: slcan lines are written into the pty of a
simulated slcan adapter while python-can's slcan interface and `CanBus`/`CanBoard` read them.

After every example a known sentinel sample follows (behind a line break, so it starts clean):
the test reads SampleBlocks until the sentinel is out, which proves the driver is still alive
and the parser recovered, and checks that every sample is finite. Structured examples (frames
with valid checksums but wild fields) also check the counters against what was sent: each such
frame is either a sample or one counted malformed frame, never lost and never an exception.
"""

from __future__ import annotations

import asyncio
import os
import tty

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.can_board import CanBoard, CanBus
from drivers.protocol import can_frames as cf
from drivers.protocol import serial_frames as sf
from drivers.serial_board import SerialBoard
from drivers.sim.slcan_pty import SimCanBoard, SimCanHub, SlcanPtyAdapter
from contracts.types import Identity

pytestmark = pytest.mark.timeout(180)

IDENT = Identity(serial="FUZZ0001", sensor="LIS3DSH", fw="1.0", ug_per_lsb=60.0, t_lsb_per_c=1.0,
                 t_lsb_at_25c=0.0, odr_hz=50.0)
SENTINEL_COUNTS = 777_777  # an x count no example produces by chance (int16 on CAN: 31_111)
CAN_SENTINEL = 31_111
NODE = 5
FUZZ = settings(max_examples=400, deadline=None, database=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

_U32, _U64, _I32 = (1 << 32) - 1, (1 << 64) - 1, (1 << 31)


def _checksum_valid_sample(line: bytes) -> bool:
    """A `$D,...*HH` line whose checksum holds (the parser may still find its fields malformed)."""
    line = line.strip()
    if not (line.startswith(b"$D,") and len(line) > 4 and line[-3:-2] == b"*"):
        return False
    body, hh = line[1:-3], line[-2:]
    try:
        return sf.checksum(body) == int(hh, 16)
    except ValueError:
        return False


def _all_finite(block) -> bool:
    return bool(np.isfinite(block.time_s).all() and np.isfinite(block.acc_g).all() and np.isfinite(block.temp_c).all())


# --- serial ---------------------------------------------------------------------------------------

class SerialRig:
    """A real pty; the test plays the board on the master fd, SerialBoard reads the slave."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.board = SerialBoard(os.ttyname(self.slave), ack_timeout_s=0.3)
        self.seq = 0
        self.examples = 0
        self.loop.run_until_complete(self._open())

    async def _open(self) -> None:
        await self.board.open()
        ident = asyncio.ensure_future(self.board.identify(timeout_s=6))
        await asyncio.sleep(0.1)  # the ID command is on the wire: answer like the firmware
        await self.write(sf.IdentityFrame(IDENT).encode())
        assert await ident == IDENT

    async def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view[:1024])
            except BlockingIOError:
                n = 0
            view = view[n:]
            await asyncio.sleep(0)  # let the driver read (its reader runs in this loop)
        self._drain_master()

    def _drain_master(self) -> None:
        try:
            while os.read(self.master, 4096):
                pass
        except (BlockingIOError, OSError):
            pass

    async def _example(self, data: bytes):
        """Writes data, then three sentinels 20 ms apart: whatever clock the garbage left behind,
        the third is taken (see ClockUnwrapper), and the read ends when it is out. Garbage holding
        three or more checksum-valid sample frames of another timeline is a stream break (a reset
        or a clock jump, design 3.1): the station then ends the run and the next run STARTs the
        stream again, so the rig does the same and sends its sentinels once more."""
        self.sentinel_batches = 1
        blocks, found, breaks = await self._send_and_read(data)
        if not found:
            assert breaks, f"sentinel not received after {data!r} (no stream break reported)"
            valid = sum(1 for line in data.split(b"\n") if _checksum_valid_sample(line))
            assert valid >= sf.StreamTimeline.CONFIRM_FRAMES, f"a break from {valid} valid frames: {data!r}"
            await self._restart()
            self.sentinel_batches = 2
            more, found, _ = await self._send_and_read(b"")
            blocks += more
        if not found:
            raise AssertionError(f"sentinel not received after {data!r} and a restart")
        return blocks

    async def _send_and_read(self, data: bytes):
        sentinels = b""
        for k in range(3):
            self.seq = (self.seq + 1) % (1 << 32)
            t_us = (1_000_000 + self.seq * 20_000) % (1 << 32)
            sentinels += sf.SampleFrame(self.seq, t_us, SENTINEL_COUNTS + k, 0, 0, 25).encode()
        await self.write(data + b"\n" + sentinels)
        blocks = []
        for _ in range(40):
            blk = await self.board.read_block(0.25)  # never raises: the link is up
            blocks.append(blk)
            if len(blk) and np.any(np.isclose(blk.acc_g[:, 0], (SENTINEL_COUNTS + 2) * 60e-6)):
                return blocks, True, []
            breaks = self.board.take_breaks()
            if breaks:
                return blocks, False, breaks
        return blocks, False, []

    async def _restart(self) -> None:
        """START, acknowledged like the firmware: a new stream, a new timeline."""
        started = asyncio.ensure_future(self.board.start())
        await asyncio.sleep(0.05)
        await self.write(sf.AckFrame("START").encode())
        await started

    def run(self, data: bytes):
        self.examples += 1
        return self.loop.run_until_complete(self._example(data))

    def close(self) -> None:
        self.loop.run_until_complete(self.board.close())
        self.loop.close()
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture(scope="module")
def serial_rig():
    rig = SerialRig()
    yield rig
    print(f"\nserial fuzz: {rig.examples} examples, stats {rig.board.stats.as_dict()}")
    rig.close()


_VALID_D = st.builds(lambda seq, t, ax, ay, az, tc: sf.SampleFrame(seq, t, ax, ay, az, tc).encode(),
                     st.integers(0, _U32), st.integers(0, _U64), *[st.integers(-_I32, _I32 - 1)] * 4)
_VALID_OTHER = st.sampled_from([sf.IdentityFrame(IDENT).encode(), sf.AckFrame("START").encode(),
                                sf.ErrorFrame("E1", "overflow").encode(), b"$A*41\n"])


@st.composite
def mutated_frames(draw) -> bytes:
    """Valid frames, then bytes flipped, inserted, deleted or cut (checksums mostly break)."""
    frames = draw(st.lists(st.one_of(_VALID_D, _VALID_OTHER), min_size=1, max_size=8))
    buf = bytearray(b"".join(frames))
    for _ in range(draw(st.integers(0, 6))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "cut"]))
        if not buf:
            break
        i = draw(st.integers(0, len(buf) - 1))
        if op == "flip":
            buf[i] ^= draw(st.integers(1, 255))
        elif op == "insert":
            buf[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del buf[i]
        else:
            del buf[i:]
    return bytes(buf)


@settings(FUZZ)
@given(data=st.one_of(st.binary(max_size=1500), mutated_frames()))
def test_serial_driver_survives_random_and_mutated_bytes(serial_rig, data):
    for blk in serial_rig.run(data):
        assert _all_finite(blk), data


_FIELD = st.one_of(
    st.integers(-(1 << 70), 1 << 70).map(str),  # in and far out of every range
    st.sampled_from(["", "nan", "inf", "-inf", "1e300", "1.5", "0x10", "--1", "9" * 40, "\u00b2"]),
)


@st.composite
def checksum_valid_sample_frames(draw) -> tuple[bytes, int]:
    """D frames whose checksum is right but whose fields may be anything; returns (bytes, how
    many of them are in range), from the generated values, not from the parser."""
    out, valid = bytearray(), 0
    for _ in range(draw(st.integers(1, 6))):
        fields = [draw(_FIELD) for _ in range(draw(st.sampled_from([6, 6, 6, 5, 7])))]
        body = ",".join(["D", *fields])
        try:
            body_bytes = body.encode("ascii")
        except UnicodeEncodeError:
            body_bytes = body.encode("utf-8")
        out += sf.encode(body_bytes)
        ok = len(fields) == 6 and all(f.lstrip("-").isascii() and f.lstrip("-").isdigit() and f.count("-") <= 1
                                      and (f[0] != "-" or len(f) > 1) for f in fields)
        if ok:
            seq, t_us, *counts = (int(f) for f in fields)
            ok = 0 <= seq <= _U32 and 0 <= t_us <= _U64 and all(-_I32 <= c < _I32 for c in counts)
        valid += ok
    return bytes(out), valid


def _split_sentinels(blocks) -> tuple[int, int]:
    """(samples of the example, sentinel samples) by their x count."""
    acc_x = np.concatenate([b.acc_g[:, 0] for b in blocks]) / 60e-6
    sentinel = np.isin(np.round(acc_x), [SENTINEL_COUNTS, SENTINEL_COUNTS + 1, SENTINEL_COUNTS + 2])
    return int((~sentinel).sum()), int(sentinel.sum())


@settings(FUZZ)
@given(case=checksum_valid_sample_frames())
def test_serial_checksum_valid_frames_are_samples_or_counted_malformed(serial_rig, case):
    """Every frame is accounted for exactly once: a sample, or one malformed frame (fields out of
    range, or a time that follows nothing: ClockUnwrapper outlier)."""
    data, n_valid = case
    n_frames = data.count(b"\n")
    s0 = serial_rig.board.stats.as_dict()
    blocks = serial_rig.run(data)
    s1 = serial_rig.board.stats.as_dict()
    n_samples, n_sentinels = _split_sentinels(blocks)
    # frames of another timeline once three of them confirmed a break: neither samples nor malformed
    after = s1["frames_after_break"] - s0["frames_after_break"]
    sent = n_frames + 3 * serial_rig.sentinel_batches
    assert all(_all_finite(b) for b in blocks)
    assert 1 <= n_sentinels <= 3 and n_samples <= n_valid
    assert s1["frames_ok"] - s0["frames_ok"] == n_samples + n_sentinels + after
    assert s1["frames_malformed"] - s0["frames_malformed"] == sent - n_samples - n_sentinels - after
    assert s1["frames_bad_checksum"] == s0["frames_bad_checksum"]


def test_a_corrupt_clock_value_on_the_wire_is_skipped_not_taken_as_a_wrap(serial_rig):
    """Issue 10: `t_us = 0xFFFFFFFF` in one checksum-valid frame moved the DUT's time 4,295 s.
    The frames are on the rig's one timeline (its sentinels' seq and clock): a stream on another
    clock would be a clock jump, which ends a run (test_a_confirmed_clock_jump_or_reset_breaks_the_stream)."""
    t0 = 1_000_000 + (serial_rig.seq + 1) * 20_000
    frames = b""
    for k in range(10):
        serial_rig.seq += 1
        t_us = 0xFFFFFFFF if k == 5 else t0 + k * 20_000
        frames += sf.SampleFrame(serial_rig.seq, t_us, 1000 + k, 0, 0, 25).encode()
    malformed0 = serial_rig.board.stats.frames_malformed
    blocks = serial_rig.run(frames)
    acc_x = np.round(np.concatenate([b.acc_g[:, 0] for b in blocks]) / 60e-6)
    time_s = np.concatenate([b.time_s for b in blocks])
    mine = (acc_x >= 1000) & (acc_x < 1010)
    ks = acc_x[mine] - 1000
    assert 5 not in ks and {6, 7, 8, 9} <= set(ks)  # the outlier skipped, the run goes on
    np.testing.assert_allclose(time_s[mine], (t0 + ks * 20_000) / 1e6 + (time_s[mine][0] - (t0 + ks[0] * 20_000) / 1e6))
    assert np.ptp(time_s[mine]) < 0.2  # no 4,295 s shift
    assert serial_rig.board.stats.frames_malformed > malformed0


# --- CAN (slcan on a pty) -------------------------------------------------------------------------

class CanRig:
    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.examples = 0
        self.seq = 0
        self.loop.run_until_complete(self._open())

    async def _open(self) -> None:
        self.hub = SimCanHub()
        self.sim = self.hub.add(SimCanBoard(NODE, IDENT))
        self.adapter = SlcanPtyAdapter(self.hub)
        self.adapter.start()
        self.bus = CanBus("slcan", self.adapter.path, 500_000, sleep_after_open=0)
        self.board = CanBoard(self.bus, NODE, sensor="LIS3DSH")
        await self.board.open()
        ident = await self.board.identify(timeout_s=6)
        assert ident.serial == IDENT.serial and ident.odr_hz == IDENT.odr_hz

    async def _example(self, lines: bytes):
        self.seq = (self.seq + 1) % 256
        sentinel = cf.encode_sample(CAN_SENTINEL, 0, 0, 0, self.seq)
        self.adapter.port.write(lines + b"\r" + b"t%03X8%s\r" % (cf.SAMPLE_BASE + NODE, sentinel.hex().upper().encode()))
        blocks = []
        for _ in range(40):
            blk = await self.board.read_block(0.25)
            blocks.append(blk)
            if len(blk) and np.any(np.isclose(blk.acc_g[:, 0], CAN_SENTINEL * 60e-6)):
                return blocks
        raise AssertionError(f"CAN sentinel not received after {lines!r} (bus error: {self.bus.error})")

    def run(self, lines: bytes):
        self.examples += 1
        return self.loop.run_until_complete(self._example(lines))

    def close(self) -> None:
        async def _close():
            await self.board.close()
            await self.bus.close()
            self.adapter.close()

        self.loop.run_until_complete(_close())
        self.loop.close()


@pytest.fixture(scope="module")
def can_rig():
    rig = CanRig()
    yield rig
    print(f"\nCAN fuzz: {rig.examples} examples, board stats {rig.board.stats.as_dict()}, "
          f"bus frames {rig.bus.frames_rx}, unreadable lines {rig.bus.frames_unreadable}")
    rig.close()


_ARB = st.one_of(st.sampled_from([cf.SAMPLE_BASE + NODE, cf.IDENT_BASE + NODE, cf.CMD_BASE + NODE,
                                  cf.SAMPLE_BASE + NODE + 1, 0x080 + NODE]), st.integers(0, 0x7FF))
_CAN_FRAME = st.builds(lambda arb, data: b"t%03X%d%s\r" % (arb, len(data), data.hex().upper().encode()),
                       _ARB, st.binary(max_size=8))


@settings(FUZZ)
@given(lines=st.lists(st.one_of(_CAN_FRAME, st.binary(max_size=40)), max_size=8).map(b"".join))
def test_can_driver_survives_wild_frames_and_line_noise(can_rig, lines):
    for blk in can_rig.run(lines):
        assert _all_finite(blk), lines
    assert can_rig.bus.error is None


def test_a_garbled_slcan_line_is_counted_and_the_bus_goes_on(can_rig):
    """Regression (found by the fuzz above): python-can's slcan parser raises on a short line or
    a non-ASCII byte, and CanBus failed the whole bus on it, faulting every CAN board."""
    before = can_rig.bus.frames_unreadable
    blocks = can_rig.run(b"t12\r" + b"t18\xff\xfe\r" + b"tZZZ8\r")
    assert can_rig.bus.error is None and sum(len(b) for b in blocks) >= 1
    assert can_rig.bus.frames_unreadable - before == 3


def test_serial_64_bit_clock_past_2_to_63_us_is_a_sample_not_a_crash(serial_rig):
    """uint64 t_us is in range (a 64-bit board clock); one past 2**63 once overflowed the block's
    int64 array and killed the read (found by the fuzz test above when it shared a block)."""
    for t_us in ((1 << 63) + 5, (1 << 64) - 2):
        frames = b"".join(sf.SampleFrame(k, t_us + k * 320_000, 1000, -1000, 16_000, 25).encode() for k in range(3))
        blocks = serial_rig.run(frames)
        assert all(_all_finite(b) for b in blocks)
