"""The CAN bus's bulk sample intake (numpy) against the frame-by-frame path it replaces.

Why: the bulk path (slcan_lines.split_frame_runs, CanBus._dispatch_run, CanBoard._on_samples) must
be a pure speed-up. Random slcan streams (sample frames of several nodes, identity and calibration
replies, seq gaps, wraps, duplicates and steps back, garbage, BEL, wrong dlc, non-hex, partial
lines, cut into reads at random places, ODR changes) are fed to two buses, one with the fast path
switched off (`bus.bulk = False`: split_frames and `_on_frame` per frame, the reference); every
sample block, counter, reply and the order of replies vs samples must come out the same.
No hardware: the buses are never opened; the test feeds `_ingest` and calls `_drain` itself.
"""

from __future__ import annotations

import asyncio
import random
import struct

import numpy as np
import pytest

from contracts.types import Identity, SampleBlock
from drivers.can_board import CanBoard, CanBus
from drivers.protocol import can_frames as cf
from drivers.protocol.slcan_lines import MAX_LINE, FrameRun, split_frame_runs, split_frames

NODES = (1, 5, 42)  # registered, identified
NO_ODR = 7  # registered, never identified: its samples cannot be timed
FOREIGN = 9  # no board claims it


def _line(arb_id: int, data: bytes, *, upper: bool = False, stamp: bool = False) -> bytes:
    text = f"t{arb_id:03X}{len(data)}{data.hex()}"
    text = text.upper().replace("T", "t", 1) if upper else text.lower()
    return text.encode() + (b"1a2b" if stamp else b"") + b"\r"


class _Stream:
    """A random slcan byte stream; seeded, so both buses see the very same bytes."""

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.seq = {n: rng.randrange(256) for n in (*NODES, NO_ODR, FOREIGN)}

    def sample(self, node: int) -> bytes:
        r = self.rng
        roll = r.random()
        if roll < 0.03:
            self.seq[node] += r.randrange(2, 40)  # a gap
        elif roll < 0.04:
            self.seq[node] += 0  # a duplicate
        elif roll < 0.05:
            self.seq[node] -= r.randrange(1, 200)  # a step back: the board restarted
        else:
            self.seq[node] += 1
        data = cf.encode_sample(r.randrange(-32768, 32768), r.randrange(-32768, 32768),
                                r.randrange(-32768, 32768), r.randrange(-128, 128), self.seq[node] & 0xFF)
        return _line(cf.SAMPLE_BASE + node, data, upper=r.random() < 0.05)

    def other(self, node: int) -> bytes:
        """Anything but a clean sample frame."""
        r = self.rng
        k = r.randrange(14)
        if k == 0:
            return _line(cf.IDENT_BASE + node, r.choice(cf.encode_identity(f"SN{node:05d}", 60.0, 100.0)))
        if k == 1:
            return _line(cf.IDENT_BASE + node, cf.encode_cal_status(r.randrange(3), r.random() < 0.5, r.getrandbits(32)))
        if k == 2:
            return _line(cf.IDENT_BASE + node, cf.encode_cal_stored_field(r.randrange(6), r.uniform(-5, 5)))
        if k == 3:
            return _line(cf.SAMPLE_BASE + node, bytes(r.randrange(256) for _ in range(r.choice((0, 5, 7)))))
        if k == 4:
            return _line(cf.CMD_BASE + node, cf.encode_command(cf.CMD_START))
        if k == 5:  # a sample frame with the adapter's timestamp: valid, but not the clean form
            self.seq[node] += 1
            return _line(cf.SAMPLE_BASE + node, cf.encode_sample(1, 2, 3, 4, self.seq[node] & 0xFF), stamp=True)
        if k == 6:  # non-hex in a sample frame
            line = bytearray(self.sample(node))
            line[r.randrange(1, len(line) - 1)] = r.choice(b"gxZ -\x00\xff")
            return bytes(line)
        if k == 7:
            return b"\x07"
        if k == 8:
            return r.choice([b"\r", b"z\r", b"Z\r", b"V1013\r", b"T0000018501020304050607\r"])
        if k == 9:  # garbage, sometimes with a terminator inside
            return bytes(r.randrange(256) for _ in range(r.randrange(1, 30)))
        if k == 10:  # a sample frame cut by a BEL
            return self.sample(node)[: r.randrange(1, 20)] + b"\x07"
        if k == 11:  # no CR for longer than any frame
            return b"t" + b"0" * (MAX_LINE + r.randrange(1, 40))
        if k == 12:  # wrong dlc digit for its payload
            return b"t1858" + b"00" * 7 + b"\r"
        return _line(cf.SAMPLE_BASE + node, cf.encode_sample(0, 0, 0, 0, 0))[:-1] + b"00\r"  # 10 bytes

    def text(self, n_lines: int, p_other: float) -> bytes:
        out = []
        for _ in range(n_lines):
            node = self.rng.choice((*NODES, *NODES, NO_ODR, FOREIGN))
            out.append(self.other(node) if self.rng.random() < p_other else self.sample(node))
        return b"".join(out)


class _Rig:
    """One bus with its boards, never opened; `log` records every non-sample frame a board takes
    with what the board held then (the order of replies vs samples)."""

    def __init__(self, bulk: bool, loop: asyncio.AbstractEventLoop) -> None:
        self.bus = CanBus("slcan", "none", None)
        self.bus.bulk = bulk
        self.buf = bytearray()
        self.log: list[tuple[int, int, bytes, float | None, int]] = []
        self.blocks: dict[int, list[SampleBlock]] = {n: [] for n in (*NODES, NO_ODR)}
        self.boards = {n: CanBoard(self.bus, n) for n in (*NODES, NO_ODR)}
        for n, b in self.boards.items():
            self.bus.register(b)
            if n != NO_ODR:
                b.identity = Identity(f"SN{n:05d}", "LIS3DSH", "", 60.0, 1.0, 0.0, 100.0 + n)
                b._rebase(100.0 + n)
            b._ident = cf.IdentityAssembler()
            b._ident_fut = loop.create_future()
            b._cal_fut = loop.create_future()
            self._spy(n, b)

    def _spy(self, node: int, board: CanBoard) -> None:
        on_frame = board._on_frame

        def logged(func: int, data: bytes) -> None:
            if func != cf.SAMPLE_BASE:
                self.log.append((node, func, data, getattr(board, "last_sample_t", None), len(board._held)))
            on_frame(func, data)
        board._on_frame = logged  # type: ignore[method-assign]

    def feed(self, chunk: bytes) -> None:
        self.buf += chunk
        self.bus._ingest(self.buf)

    def take(self) -> None:
        for n, b in self.boards.items():
            self.blocks[n].append(b._held.take_block(b.identity))

    def state(self) -> dict[str, object]:
        bus = self.bus
        out: dict[str, object] = {
            "bus": (bus.frames_rx, bus.frames_foreign, bus.frames_unreadable, bus._frames_queued, len(bus._inbox)),
            "buf": bytes(self.buf), "log": self.log}
        for n, b in self.boards.items():
            s = b._seq
            fut = [f.result() if f is not None and f.done() else None for f in (b._ident_fut, b._cal_fut)]
            out[f"board{n}"] = (b.stats.as_dict(), (s.index, s.last, s.lost, s.resyncs), getattr(b, "last_sample_t", None),
                                b._held._lost, len(b._held), b._ident, list(b._cal_fields), fut,
                                b._time_base_s, b._index_base, b._odr_hz, b.backlog_samples())
        return out


def _same_blocks(got: list[SampleBlock], want: list[SampleBlock]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g.lost_samples == w.lost_samples
        for a, b in ((g.time_s, w.time_s), (g.acc_g, w.acc_g), (g.temp_c, w.temp_c)):
            assert a.dtype == b.dtype and a.shape == b.shape
            np.testing.assert_array_equal(a, b)  # bit for bit, not close


def _run_both(seed: int, n_lines: int, p_other: float) -> tuple[_Rig, _Rig]:
    loop = asyncio.get_running_loop()
    rng = random.Random(seed)
    data = _Stream(rng).text(n_lines, p_other)
    fast, ref = _Rig(True, loop), _Rig(False, loop)
    pos = 0
    while pos < len(data):
        step = rng.choice((1, 7, 23, 100, 512, 4096))
        chunk, pos = data[pos:pos + rng.randrange(1, step + 1)], pos + step
        for rig in (fast, ref):
            rig.feed(chunk)
        roll = rng.random()
        if roll < 0.3:
            for rig in (fast, ref):
                rig.bus._drain()
        if roll < 0.05:
            for rig in (fast, ref):
                rig.take()
        if roll > 0.995:  # an ODR change between reads: time stays continuous (CanBoard._rebase)
            node, odr = rng.choice(NODES), rng.choice((50.0, 100.0, 400.0, 3.125))
            for rig in (fast, ref):
                rig.boards[node]._rebase(odr)
    for rig in (fast, ref):
        rig.bus._drain()
        rig.take()
    return fast, ref


@pytest.mark.parametrize("min_group", [1, cf.MIN_GROUP])
@pytest.mark.parametrize("seed", range(30))
async def test_bulk_equals_frame_by_frame(seed: int, min_group: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cf, "MIN_GROUP", min_group)  # 1: every node's group through the bulk path
    p_other = (0.0, 0.002, 0.02, 0.2, 0.6)[seed % 5]
    fast, ref = _run_both(seed, 3000, p_other)
    for n in fast.blocks:
        _same_blocks(fast.blocks[n], ref.blocks[n])
    assert fast.state() == ref.state()
    assert sum(len(b) for n in NODES for b in ref.blocks[n]) > 0


async def test_clean_stream_takes_the_fast_path() -> None:
    """Not vacuous: on a clean stream almost no frame goes through `_on_frame`."""
    fast, ref = _run_both(1000, 5000, 0.0)
    for n in NODES:
        _same_blocks(fast.blocks[n], ref.blocks[n])
    assert fast.state() == ref.state()
    calls = 0
    board = CanBoard(CanBus("slcan", "none", None), 3)
    board.bus.register(board)
    board.identity = Identity("X", "LIS3DSH", "", 60.0, 1.0, 0.0, 100.0)
    on_frame = board._on_frame

    def counted(func: int, data: bytes) -> None:
        nonlocal calls
        calls += 1
        on_frame(func, data)
    board._on_frame = counted  # type: ignore[method-assign]
    buf = bytearray(b"".join(_line(cf.SAMPLE_BASE + 3, cf.encode_sample(k, -k, 2 * k, 1, k & 0xFF))
                             for k in range(1000)))
    board.bus._ingest(buf)
    board.bus._drain()
    blk = board._held.take_block(board.identity)
    assert calls == 1 and len(blk) == 1000 and blk.lost_samples == 0  # only the very first frame
    np.testing.assert_array_equal(blk.time_s, np.arange(1000) / 100.0)


@pytest.mark.parametrize("seed", range(30))
def test_split_frame_runs_equals_split_frames(seed: int) -> None:
    rng = random.Random(seed)
    data = _Stream(rng).text(400, (0.0, 0.1, 0.5)[seed % 3])
    a, b = bytearray(), bytearray()
    pos = 0
    while pos < len(data):
        step = rng.randrange(1, 300)
        a += data[pos:pos + step]
        b += data[pos:pos + step]
        pos += step
        items, garbled = split_frame_runs(a)
        frames: list[tuple[int, bytes]] = []
        for it in items:
            frames.extend(it.frame(k) for k in range(len(it))) if isinstance(it, FrameRun) else frames.append(it)
        assert (frames, garbled) == split_frames(b)
        assert a == b


def test_decode_samples_matches_decode_sample() -> None:
    rng = np.random.default_rng(7)
    data = rng.integers(0, 256, size=(500, 8), dtype=np.uint8)
    counts, seq = cf.decode_samples(data)
    for k in range(len(data)):
        s = cf.decode_sample(data[k].tobytes())
        assert (counts[k].tolist(), int(seq[k])) == ([s.ax, s.ay, s.az, s.t], s.seq)
    assert struct.calcsize("<hhhbB") == 8
