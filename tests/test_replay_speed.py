"""The replay's boards put the same bytes on the wire when their frames are rendered in bulk (issue 40).

A replay renders each serial DUT's record as design-3.1 `D` frames ahead, with numpy
(drivers/sim/serial_pty.render_sample_frames, drivers/sim/replay.RenderedRecord), and
SimSerialBoard.feed renders a block the same way. The independent truth here is the per-sample
encoder of the protocol module (`SampleFrame.encode`: a Python format and an XOR per frame): every
frame must be byte for byte what it gives, for random records and for the edge values a board can
send (0, -1, int32 and int64 limits, digits-count boundaries, seq wrapping past 2^32, lost samples).
"""

from __future__ import annotations

import os
import select

import numpy as np

from contracts.recording import RecordedDut
from contracts.types import Identity
from drivers.protocol import serial_frames as sf
from drivers.sim.replay import FRAME_CHUNK, RenderedRecord
from drivers.sim.serial_pty import SimSerialBoard, render_sample_frames

INT64_MIN, INT64_MAX = -(1 << 63), (1 << 63) - 1
EDGES = [0, -1, 1, 9, 10, -9, -10, 99, 100, 9999, 10000, -9999, -10000, 99999999, 100000000,
         (1 << 31) - 1, -(1 << 31), (1 << 32) - 1, 10 ** 18 - 1, 10 ** 18, INT64_MIN, INT64_MAX]


def _reference(seq, t_us, acc, temp) -> list[bytes]:
    return [sf.SampleFrame(int(s), int(t), int(a[0]), int(a[1]), int(a[2]), int(c)).encode()
            for s, t, a, c in zip(seq, t_us, acc, temp)]


def _frames(data: bytes, off: np.ndarray) -> list[bytes]:
    return [data[off[k]:off[k + 1]] for k in range(len(off) - 1)]


def test_bulk_rendered_frames_are_the_per_sample_encoders_bytes():
    rng = np.random.default_rng(40)
    edges = np.array(EDGES, dtype=np.int64)
    for n, lo, hi in ((1, -5, 5), (7, -(1 << 31), 1 << 31), (3000, -(1 << 62), 1 << 62), (500, 0, 10)):
        seq = rng.integers(0, 1 << 32, n)
        t_us = rng.integers(lo, hi, n)
        acc = rng.integers(lo, hi, (n, 3))
        temp = rng.integers(lo, hi, n)
        k = min(n, len(edges))  # edge values in every column, in several rows
        t_us[:k], temp[:k], acc[:k, 0], acc[:k, 1], acc[:k, 2] = (edges[:k], edges[::-1][:k], edges[:k],
                                                                   np.roll(edges, 3)[:k], -np.abs(edges[:k] // 7))
        data, off = render_sample_frames(seq, t_us, acc, temp)
        ref = _reference(seq, t_us, acc, temp)
        assert _frames(data, off) == ref
        assert data == b"".join(ref)
    # and the station's parser reads in-range frames back as the samples rendered
    i32 = [-(1 << 31), -1, 0, 9, 10, (1 << 31) - 1]
    seq = np.array([0, 9, 10, (1 << 32) - 1, 99999, 100000], dtype=np.int64)
    t_us = np.array([0, 1, 10 ** 12, INT64_MAX, 99, 100], dtype=np.int64)
    acc = np.array([i32, i32[::-1], i32[2:] + i32[:2]], dtype=np.int64).T
    data, _ = render_sample_frames(seq, t_us, acc, acc[:, 0])
    frames = sf.FrameParser().feed(data)
    assert [(f.seq, f.t_us, f.ax, f.ay, f.az, f.t) for f in frames] == [
        (int(s), int(t), *map(int, a), int(a[0])) for s, t, a in zip(seq, t_us, acc)]
    data, off = render_sample_frames(np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros(0))
    assert data == b"" and list(off) == [0]


def _record(n: int, rng: np.random.Generator) -> RecordedDut:
    ident = Identity(serial="SPD0001", sensor="LOG", fw="replay", ug_per_lsb=0.1, t_lsb_per_c=1e4,
                     t_lsb_at_25c=0.0, odr_hz=3.125)
    # lost samples (gaps of 3 and 6 periods) make the seq skip, as the replay board sends it
    time_s = 12345.678 + np.cumsum(rng.choice([0.32, 0.32, 0.32, 0.32, 0.96, 1.92], n))
    return RecordedDut(slot="r01", serial="SPD0001", link="serial", identity=ident, time_s=np.round(time_s, 6),
                       acc_counts=rng.integers(-(1 << 31), 1 << 31, (n, 3)), temp_counts=rng.integers(-9, 600000, n),
                       lamp=None, position=None, outcome={})


def test_a_record_rendered_in_chunks_sends_what_the_board_formatted_sample_by_sample():
    rng = np.random.default_rng(7)
    d = _record(3 * FRAME_CHUNK + 123, rng)
    seq = d.seq_index() + (1 << 32) - 1000  # wraps past 2^32 within the record
    assert np.any(np.diff(seq) > 1)
    t_us = np.round(d.time_s * 1e6).astype(np.int64)
    ref = _reference(seq & 0xFFFFFFFF, t_us, d.acc_counts, d.temp_counts)
    r = RenderedRecord(d, seq)
    assert 0 < r.prerender(1) < 1 << 20  # a budget: one chunk, not the whole record
    # sent forward in pieces of any length, across chunk borders, as ReplayWorld sends it
    cuts = np.sort(rng.choice(np.arange(1, len(d)), 60, replace=False))
    bounds = [0, 1, *cuts.tolist(), FRAME_CHUNK * 2 - 1, FRAME_CHUNK * 2 + 1, len(d)]
    bounds = sorted(set(bounds))
    sent = [r.frames(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    assert b"".join(sent) == b"".join(ref)
    assert len(r._chunks) <= 2  # chunks behind the pieces sent are dropped


def _read_all(fd: int) -> bytes:
    out = b""
    while select.select([fd], [], [], 0.2)[0]:
        got = os.read(fd, 1 << 16)
        if not got:
            break
        out += got
    return out


def test_a_board_feed_puts_the_per_sample_frames_on_its_pty():
    """SimSerialBoard.feed renders a block in bulk too; with a 32-bit clock that wraps, a seq that
    wraps and a corrupted frame (one wrong checksum, the rest intact)."""
    rng = np.random.default_rng(11)
    ident = Identity(serial="SPD0002", sensor="LIS3DSH", fw="sim", ug_per_lsb=60.0, t_lsb_per_c=1.0,
                     t_lsb_at_25c=0.0, odr_hz=100.0)
    board = SimSerialBoard(ident, t0_us=(1 << 32) - 50_000)
    slave = os.open(board.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        board.streaming, board.seq = True, (1 << 32) - 3
        n = 40
        time_s = np.arange(n) / 100.0
        acc = rng.integers(-32768, 32768, (n, 3))
        temp = rng.integers(-128, 128, n)
        board.corrupt_next(1)
        board.feed(time_s, acc, temp)
        got = _read_all(slave)
        seq = ((1 << 32) - 3 + np.arange(n)) & 0xFFFFFFFF
        t_us = (np.round(time_s * 1e6).astype(np.int64) + (1 << 32) - 50_000) & 0xFFFFFFFF
        ref = _reference(seq, t_us, acc, temp)
        lines = got.splitlines(keepends=True)
        assert lines[1:] == ref[1:] and lines[0] != ref[0] and lines[0][:-4] == ref[0][:-4]
        assert board.seq == int(seq[-1]) + 1 & 0xFFFFFFFF and board.frames_sent == n
    finally:
        os.close(slave)
        board.close()
