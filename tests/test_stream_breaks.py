"""One board, one timeline (issue 36): a board that restarts while streaming, or whose clock jumps,
ends its run with that reason; garbage that passed the checksum never does.

Pure: drivers/protocol/serial_frames.StreamTimeline on (seq, t_us) sequences written here. Wire:
the serial driver (pyserial on a real pty) against a simulated board that resets and streams again
by itself or jumps its clock: the break is reported once, counted in the link's stats, and no
sample after it is delivered (they are another timeline's).
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from contracts.types import Identity
from drivers.protocol.serial_frames import StreamTimeline
from drivers.serial_board import SerialBoard
from drivers.sim.serial_pty import SimSerialBoard

PERIOD_US = 320_000  # LIS3DSH at 3.125 Hz


def _feed(tl: StreamTimeline, frames) -> list[str]:
    return [tl.check(seq, t) for seq, t in frames]


def _steady(n: int, seq0: int = 0, t0: int = 5_000_000) -> list[tuple[int, int]]:
    return [(seq0 + k, t0 + k * PERIOD_US) for k in range(n)]


def test_a_steady_stream_with_lost_frames_and_a_clock_wrap_is_one_line():
    tl = StreamTimeline()
    frames = _steady(10)
    frames += [(15, frames[-1][1] + 6 * PERIOD_US)]  # five frames lost: seq and clock agree
    wrap0 = (1 << 32) - 2 * PERIOD_US
    frames += [(16 + k, (wrap0 + k * PERIOD_US) % (1 << 32)) for k in range(6)]  # rebase, then wrap
    out = _feed(tl, frames[:11])
    assert out == ["ok"] * 11
    assert _feed(StreamTimeline(), [(k, (wrap0 + k * PERIOD_US) % (1 << 32)) for k in range(8)]) == ["ok"] * 8


def test_one_or_two_frames_off_the_line_are_skipped_never_a_break():
    tl = StreamTimeline()
    frames = _steady(10)
    frames.insert(5, (5, 4_294_967_295))  # a corrupt clock that passed the checksum
    frames.insert(8, (123456, 77))  # a corrupt seq
    frames.insert(9, (123457, 77 + PERIOD_US))  # and a second one agreeing with it: still not 3
    out = _feed(tl, frames)
    assert out.count("skip") == 3 and out.count("ok") == 10, out


@pytest.mark.parametrize("case, expect", [
    ("reset", "reset"),  # seq from 0, clock from power-up
    ("back 600 s", "clock_jump"),
    ("forward 600 s", "clock_jump"),
])
def test_three_agreeing_frames_on_another_timeline_are_a_break(case, expect):
    tl = StreamTimeline()
    frames = _steady(20, seq0=48_000)
    seq, t = frames[-1]
    if case == "reset":
        after = [(k, 50_000 + k * PERIOD_US) for k in range(5)]
    else:
        shift = (-600 if case.startswith("back") else 600) * 1_000_000
        after = [(seq + 1 + k, t + shift + (k + 1) * PERIOD_US) for k in range(5)]
    out = _feed(tl, frames + after)
    assert out[:20] == ["ok"] * 20
    assert out[20:23] == ["skip", "skip", expect], out[20:]
    assert out[23:] == ["ok", "ok"]  # the new line (the driver takes nothing after a break)


def test_a_short_forward_gap_with_the_seq_running_on_is_a_gap_not_a_break():
    """A board that stalled (a flash write, an overrun) and took no samples for 2 s, counting on."""
    tl = StreamTimeline()
    frames = _steady(10)
    seq, t = frames[-1]
    frames += [(seq + 1 + k, t + 2_000_000 + k * PERIOD_US) for k in range(4)]
    out = _feed(tl, frames)
    assert "reset" not in out and "clock_jump" not in out and out[12] == "gap", out


@pytest.mark.parametrize("silent_wall_s, expect", [(1.0, "gap"), (0.05, "clock_jump")])
def test_a_long_forward_step_is_a_gap_only_when_the_board_was_silent_that_long(silent_wall_s, expect):
    """x100 (timing.speed): 82 s of sample time forward with the seq running on is a board that took
    no samples for 0.8 s of wall time (a muted sensor, a stalled firmware) when its frames really
    stopped for that long; arriving 50 ms after the one before, it is a clock that jumped."""
    tl = StreamTimeline(speed=100.0)
    frames = _steady(10)
    wall = [k * 0.0032 for k in range(10)]  # 3.125 Hz at x100
    seq, t = frames[-1]
    frames += [(seq + 1 + k, t + 82_000_000 + k * PERIOD_US) for k in range(3)]
    wall += [wall[-1] + silent_wall_s + k * 0.0032 for k in range(3)]
    out = [tl.check(q, u, w) for (q, u), w in zip(frames, wall)]
    assert out[10:] == ["skip", "skip", expect], out


def test_garbage_before_a_stream_has_a_line_breaks_nothing():
    """Six copies of one checksum-valid frame, then the real stream: no line existed to break."""
    tl = StreamTimeline()
    out = _feed(tl, [(0, 0)] * 6 + _steady(6, seq0=1, t0=1_020_000))
    assert "reset" not in out and "clock_jump" not in out and out[-3:] == ["ok"] * 3, out


# ---------------------------------------------------------------------------------- on the wire
IDENT = Identity(serial="TL0001", sensor="LIS3DSH", fw="1.0", ug_per_lsb=60.0, t_lsb_per_c=1.0,
                 t_lsb_at_25c=0.0, odr_hz=50.0)


async def _stream(board: SimSerialBoard, t0_s: float, n: int) -> float:
    time_s = t0_s + np.arange(n) / IDENT.odr_hz
    board.feed(time_s, np.tile([9616, 9616, 9616], (n, 1)), np.full(n, 0))
    await asyncio.sleep(0.05)
    return float(time_s[-1]) + 1 / IDENT.odr_hz


async def _read_all(drv: SerialBoard) -> np.ndarray:
    times = []
    for _ in range(5):
        blk = await drv.read_block(0.1)
        times.append(blk.time_s)
    return np.concatenate(times)


@pytest.mark.parametrize("fault", ["reset", "clock back", "clock forward"])
async def test_the_driver_reports_a_break_once_counts_it_and_delivers_nothing_after_it(fault):
    board = SimSerialBoard(IDENT, t0_us=3_000_000)
    board.start()
    drv = SerialBoard(board.path)
    try:
        await drv.open()
        await drv.identify(2.0)
        await drv.start()
        t = await _stream(board, 100.0, 50)
        before = await _read_all(drv)
        assert len(before) == 50 and not drv.take_breaks()
        if fault == "reset":
            board.reset_streaming()
        else:
            board.jump_clock(-600.0 if fault == "clock back" else 600.0)
        await _stream(board, t, 50)
        after = await _read_all(drv)
        breaks = drv.take_breaks()
        assert len(after) == 0, after  # nothing of the other timeline
        assert len(breaks) == 1 and not drv.take_breaks()
        b = breaks[0]
        assert b.kind == ("reset" if fault == "reset" else "clock_jump")
        assert b.at_t_s == pytest.approx(before[-1])
        words = {"reset": "restarted", "clock back": "600.0 s back", "clock forward": "600.0 s forward"}[fault]
        assert words in b.reason, b.reason
        stats = drv.stats.as_dict()
        assert (stats["resets"], stats["clock_jumps"]) == ((1, 0) if fault == "reset" else (0, 1))
        assert stats["frames_after_break"] >= 1  # counted, not taken
        # the next run (START) starts a new timeline: its samples are taken again (the clock
        # unwrapper spends at most one sample on a clock that moved back while it was stopped)
        await drv.start()
        await _stream(board, t + 2.0, 20)
        assert len(await _read_all(drv)) >= 19 and not drv.take_breaks()
    finally:
        await drv.close()
        board.close()
