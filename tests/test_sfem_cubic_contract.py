"""The version-2 record (docs/design.md 3.1, "cubic thermal SFEM"): the station's statement
of it (contracts/sfem_cubic.py), its frames (drivers/protocol/serial_frames.py SFTW/SFTC/SFTR/T) and
the driver's write/read (drivers/serial_board.py) against a board written from the contract alone
(tests/contract_v2_peer.py, a real pty), with every truth computed here independently: the CRC from
zlib over struct-packed float32, the compensation sample by sample in plain Python.
"""

from __future__ import annotations

import math
import struct
import zlib
from functools import reduce
from operator import xor

import numpy as np
import pytest

from contract_v2_peer import ContractPeer
from contracts.sfem_cubic import SfemCubicRecord
from drivers.base import CalibrationError
from drivers.protocol import serial_frames as sf
from drivers.serial_board import SerialBoard


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _coef(seed: int = 1) -> list[list[float]]:
    """A plausible cubic SFEM: A near identity with small thermal terms, b in g, tiny cubic terms
    (down to 1e-10: numbers whose positional text alone would overrun a line)."""
    rng = np.random.default_rng(seed)
    c0 = [*(np.eye(3).reshape(-1) + rng.normal(0, 2e-3, 9)), *rng.normal(0, 0.02, 3)]
    c1 = list(rng.normal(0, 3e-5, 12))
    c2 = list(rng.normal(0, 2e-7, 12))
    c3 = list(rng.normal(0, 3e-10, 12))
    return [[float(v) for v in row] for row in (c0, c1, c2, c3)]


def _record(seed: int = 1) -> SfemCubicRecord:
    return SfemCubicRecord(25.0, -10.0, 85.3, tuple(map(tuple, _coef(seed))))


# ---- the record ----------------------------------------------------------------------------------

def test_crc_is_zlib_of_the_51_float32_le_values_in_contract_order():
    rec = _record()
    coef = _coef()
    values = [25.0, -10.0, 85.3] + [v for row in coef for v in row]
    want = zlib.crc32(struct.pack("<51f", *values)) & 0xFFFFFFFF  # struct rounds each to float32
    assert rec.crc32() == want
    assert rec.to_f32().crc32() == want  # rounding twice changes nothing
    # the order is the contract's: swapping two powers changes the CRC
    swapped = SfemCubicRecord(25.0, -10.0, 85.3, (tuple(coef[1]), tuple(coef[0]), tuple(coef[2]), tuple(coef[3])))
    assert swapped.crc32() != want
    # to_f32 holds exactly the float32 values (85.3 is not one), -0.0 becomes 0.0
    r32 = SfemCubicRecord(25.0, -10.0, 85.3, ((-0.0,) * 12, *map(tuple, coef[1:]))).to_f32()
    assert r32.t_hi_c == _f32(85.3) != 85.3
    assert all(math.copysign(1.0, v) == 1.0 for v in r32.coef[0])
    assert r32.values() == tuple(_f32(v) for v in [25.0, -10.0, 85.3, *[0.0] * 12, *[v for row in coef[1:] for v in row]])


@pytest.mark.parametrize("change,words", [
    (dict(coef=((1.0,) * 12,) * 3), "4 x 12"),
    (dict(coef=((1.0,) * 11,) * 4), "4 x 12"),
    (dict(t_lo_c=90.0), "t_lo_c < t_hi_c"),
    (dict(t_lo_c=85.3, t_hi_c=85.3), "t_lo_c < t_hi_c"),
    (dict(t_ref_c=float("nan")), "finite"),
    (dict(coef=((1.0,) * 12, (1.0,) * 12, (float("inf"),) + (0.0,) * 11, (0.0,) * 12)), "c[2][0]"),
])
def test_invalid_records_are_refused(change, words):
    kw = dict(t_ref_c=25.0, t_lo_c=-10.0, t_hi_c=85.3, coef=tuple(map(tuple, _coef())))
    kw.update(change)
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
        SfemCubicRecord(**kw)


def test_to_f32_refuses_what_float32_cannot_hold():
    rec = SfemCubicRecord(25.0, 20.0, 20.000000001, tuple(map(tuple, _coef())))  # distinct in float64 only
    with pytest.raises(ValueError, match="t_lo_c < t_hi_c"):
        rec.to_f32()
    big = SfemCubicRecord(25.0, -10.0, 85.0, ((1e39,) + (0.0,) * 11, *map(tuple, _coef()[1:])))
    with pytest.raises(ValueError, match="not finite"):
        big.to_f32()


def test_compensate_counts_is_the_contract_sample_by_sample():
    """The numpy statement against the contract's formula written out per sample in plain floats,
    temperatures inside and beyond the record's range (clamped), with the float32 coefficients."""
    rec = _record(7)
    r = rec.to_f32()
    ug = 3.9
    lsb_g = ug * 1e-6
    rng = np.random.default_rng(3)
    raw = rng.integers(-300_000, 300_000, (40, 3))
    temp = np.concatenate([rng.uniform(-10.0, 85.3, 30), [-40.0, -10.0, 85.3, 120.0, 25.0, 200.0, -11.0, 86.0, 0.0, 60.0]])
    got = rec.compensate_counts(raw, temp, ug)
    for n in range(len(raw)):
        t = min(max(float(temp[n]), r.t_lo_c), r.t_hi_c)
        d = t - r.t_ref_c
        m = [sum(r.coef[k][j] * d ** k for k in range(4)) for j in range(12)]
        x = [float(raw[n][i]) - m[9 + i] / lsb_g for i in range(3)]
        want = [sum(m[3 * i + j] * x[j] for j in range(3)) for i in range(3)]
        assert got[n] == pytest.approx(want, rel=1e-12, abs=1e-9), n
    # clamping is real: beyond the range the output equals the one at the range's (float32) edge
    edge = rec.compensate_counts(raw[:1], [r.t_hi_c], ug)
    np.testing.assert_array_equal(rec.compensate_counts(raw[:1], [200.0], ug), edge)
    assert not np.array_equal(rec.compensate_counts(raw[:1], [60.0], ug), edge)


# ---- the frames ----------------------------------------------------------------------------------

def _xor_frame(body: str) -> bytes:
    raw = body.encode()
    return b"$%s*%02X\n" % (raw, reduce(xor, raw, 0))


def test_sftw_sftc_sftr_frames_encode_and_parse_back_exactly():
    rec = _record(5).to_f32()
    cmds = sf.sfem_cubic_commands(rec)
    assert len(cmds) == 5
    board = sf.FrameParser(board_side=True)
    got = board.feed(b"".join(cmds) + sf.cmd_sftr("H") + sf.cmd_sftr(3))
    assert board.stats.frames_malformed == 0 and board.stats.frames_bad_checksum == 0
    assert [g.command for g in got] == ["SFTW"] * 4 + ["SFTC", "SFTR", "SFTR"]
    for k in range(4):
        assert got[k].args[0] == str(k)
        # what the board reads (decimal -> float64 -> float32) is exactly the stored float32
        assert [_f32(float(x)) for x in got[k].args[1:]] == list(rec.coef[k])
        assert len(cmds[k]) < 200  # the board's line buffer (FW_RX_LINE_MAX)
    t_ref, t_lo, t_hi, crc = got[4].args
    assert [_f32(float(x)) for x in (t_ref, t_lo, t_hi)] == [rec.t_ref_c, rec.t_lo_c, rec.t_hi_c]
    assert int(crc, 16) == zlib.crc32(struct.pack("<51f", *rec.values()))
    assert got[5].args == ("H",) and got[6].args == ("3",)
    for cmd in cmds:  # framing: the checksum is the XOR of the body
        assert cmd == _xor_frame(cmd[1:-4].decode())
    with pytest.raises(ValueError):
        sf.cmd_sftr(4)
    with pytest.raises(ValueError):
        sf.cmd_sftw(0, [1.0] * 11)


def test_t_frames_decode_and_bad_ones_are_counted():
    p = sf.FrameParser()
    vals = [1.0, 0.5, -0.25, 0.0, 1.0000001, 0.0, 0.0, 0.0, 1.0, 0.001, -0.002, 3e-12]
    got = p.feed(_xor_frame("T,H,25,-10,85.3,0A1B2C3D") + _xor_frame("T,2," + ",".join(repr(v) for v in vals))
                 + _xor_frame("T,4," + ",".join("0" * 12)) + _xor_frame("T,1,1,2") + _xor_frame("T,H,25,-10,nan,0A1B2C3D")
                 + _xor_frame("T,H,25,-10,85,XYZ"))
    assert got == [sf.SfemCubicHeadFrame(25.0, -10.0, _f32(85.3), 0x0A1B2C3D),
                   sf.SfemCubicRowFrame(2, tuple(_f32(v) for v in vals))]
    assert p.stats.frames_malformed == 4 and p.stats.frames_ok == 2
    # the station's own encoders give what it decodes
    assert sf.FrameParser().feed(got[0].encode() + got[1].encode()) == got


# ---- the driver against a board written from the contract ------------------------------------------

@pytest.fixture
async def peer_board():
    peer = ContractPeer(extras=",reset=power,boots=1,rec_ver=1,rec_gen=3,rec_slot=0,rec_state=ok,caps=scal+sfem3")
    drv = SerialBoard(peer.path, ack_timeout_s=0.3)
    await drv.open()
    try:
        await drv.identify()
        yield peer, drv
    finally:
        await drv.close()
        peer.close()


async def test_write_then_read_sfem_cubic(peer_board):
    peer, drv = peer_board
    assert drv.supports_sfem_cubic and drv.supports_selfcal
    rec = _record(11)
    want_crc = zlib.crc32(struct.pack("<51f", *rec.values())) & 0xFFFFFFFF
    assert await drv.write_sfem_cubic(rec) == want_crc
    assert peer.stored is not None and peer.stored[1] == want_crc
    assert [c[0] for c in peer.commands[1:]] == ["SFTW"] * 4 + ["SFTC"]
    back = await drv.read_sfem_cubic()
    assert back == rec.to_f32() and back.crc32() == want_crc
    assert drv.stats.frames_malformed == 0 and drv.stats.frames_bad_checksum == 0


async def test_sfem_cubic_failures_are_calibration_errors(peer_board):
    peer, drv = peer_board
    rec = _record(12)
    with pytest.raises(CalibrationError) as exc:  # nothing stored yet
        await drv.read_sfem_cubic()
    assert exc.value.kind == "refused" and "no cubic SFEM stored" in str(exc.value)
    # one attempt per call (the caller's policy retries, as program_thermal does): a lost ack ...
    peer.drop_acks = 1
    with pytest.raises(CalibrationError) as exc:
        await drv.write_sfem_cubic(rec)
    assert exc.value.kind == "no_reply" and "SFTW,0" in str(exc.value)
    assert "SFTC" not in [c[0] for c in peer.commands]  # no commit after a power that was not staged for sure
    # ... a board that answers another CRC ...
    peer.wrong_crc = 1
    with pytest.raises(CalibrationError) as exc:
        await drv.write_sfem_cubic(rec)
    assert exc.value.kind == "crc_mismatch" and f"{rec.crc32() ^ 1:08X}" in str(exc.value)
    # ... a board that refuses the commit ...
    peer.refuse_commit = 1
    with pytest.raises(CalibrationError) as exc:
        await drv.write_sfem_cubic(rec)
    assert exc.value.kind == "refused" and "flash write failed" in str(exc.value)
    # ... and the next call stores it
    assert await drv.write_sfem_cubic(rec) == rec.crc32() and peer.stored is not None
    # a stored record whose values are not what its CRC names: the read-back says so
    peer.stored_flip = True
    await drv.write_sfem_cubic(rec)
    with pytest.raises(CalibrationError) as exc:
        await drv.read_sfem_cubic()
    assert exc.value.kind == "readback_mismatch"
