"""The serial driver's bulk path (drivers/protocol/sample_lines.py and SerialBoard._take_clean)
gives exactly what the per-line parser gives: the same samples, losses, counters and breaks, on
random streams with everything a line can carry (gaps, garbage, bad checksums, replies among the
samples, signs and leading zeros, 20-digit numbers, a 32-bit clock wrap, a board reset, a clock
jump), cut into reads at random places. The per-line path is the independent definition."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.protocol import serial_frames as sf
from drivers.protocol.sample_lines import decode_sample_lines
from drivers.serial_board import SerialBoard


def _line(body: str) -> bytes:
    return sf.encode(body)


def _stream(rng: np.random.Generator, n: int) -> bytes:
    period = int(rng.choice([320_000, 10_000, 8_000, 1_000]))
    seq = int(rng.integers(0, 1 << 32)) if rng.random() < 0.3 else 0
    t = int(rng.integers((1 << 32) - period * n // 2, 1 << 32)) if rng.random() < 0.3 else int(rng.integers(0, 10**9))
    out = []
    for _ in range(n):
        r = rng.random()
        jitter = int(rng.integers(-period // 50, period // 50 + 1))
        counts = [int(v) for v in rng.integers(-40000, 40000, 3)] + [int(rng.integers(-500, 2000))]
        if r < 0.01:
            seq += int(rng.integers(2, 6))  # lost samples
            t += period * 3
        elif r < 0.012:
            seq, t = 0, int(rng.integers(0, 10**6))  # the board reset
        elif r < 0.014:
            t += 50_000_000  # clock jump
        else:
            seq += 1
            t += period + jitter
        seq %= 1 << 32
        tw = t % (1 << 32)
        body = f"D,{seq},{tw},{counts[0]},{counts[1]},{counts[2]},{counts[3]}"
        q = rng.random()
        if q < 0.005:
            out.append(b"garbage\n")
        elif q < 0.01:
            raw = bytearray(_line(body))
            raw[4] ^= 0x01  # bad checksum
            out.append(bytes(raw))
        elif q < 0.013:
            out.append(_line("A,COMP,1"))
        elif q < 0.016:
            out.append(_line(body.replace(f",{counts[0]},", f",+{abs(counts[0])},")))  # a sign the contract has not
        elif q < 0.018:
            out.append(_line(body.replace("D,", "D,000", 1)))  # leading zeros
        elif q < 0.02:
            out.append(_line(f"D,{seq},{tw},99999999999999999999,1,2,3"))  # out of range
        elif q < 0.022:
            out.append(_line(body).replace(b"\n", b"\r\n"))
        else:
            out.append(_line(body))
    return b"".join(out)


def _run(data: bytes, cuts: list[int], bulk: bool) -> tuple:
    b = SerialBoard("loop://")
    if not bulk:
        b._parser.feed_samples = lambda d: (b._parser._buf.extend(d), None)[1]  # type: ignore[method-assign]
    last = 0
    for c in cuts + [len(data)]:
        b._feed(data[last:c])
        last = c
    blk = b._held.take_block(None)
    return (blk.time_s, blk.acc_g, blk.temp_c, blk.lost_samples, b.stats.as_dict(),
            [(x.kind, x.at_t_s) for x in b.take_breaks()])


@pytest.mark.parametrize("seed", range(40))
def test_bulk_path_equals_the_per_line_parser(seed):
    rng = np.random.default_rng(seed)
    data = _stream(rng, int(rng.integers(50, 1500)))
    cuts = sorted(int(c) for c in rng.integers(0, len(data), int(rng.integers(1, 40))))
    fast, slow = _run(data, cuts, True), _run(data, cuts, False)
    for a, b_ in zip(fast[:3], slow[:3]):
        assert np.array_equal(a, b_)
    assert fast[3:] == slow[3:]


def test_clean_lines_decode_and_anything_doubtful_is_left_to_the_per_line_parser():
    ok = b"".join(_line(f"D,{k},{1000 * k},{-k},{k},7,-300") for k in range(5))
    got = decode_sample_lines(ok)
    assert got is not None and got.seq.tolist() == [0, 1, 2, 3, 4] and got.counts[:, 0].tolist() == [0, -1, -2, -3, -4]
    for bad in (_line("D,1,2,3,4,5"), _line("D,1,2,3,4,5,6,7"), _line("D,1,2,3,4,5,-"), _line("D,1,2,3,-4-,5,6"),
                _line("D,1,2,3,4,5,6").replace(b"*", b"*0"), _line("A,COMP,1"), _line("D,-1,2,3,4,5,6"),
                _line("D,1,2,3,4,5,2147483648"), _line("D,1,2,3,4,5, 6"), b"$D,1,2,3,4,5,6*00\n"):
        assert decode_sample_lines(ok + bad) is None, bad
