"""Calibration write-back frames (design 3.1 $CALW/$CALR/$SFEW/$SFER/$COMP, 3.2 0x05-0x08 and
replies 0x580+N indices 4-10): the exact bytes on the wire, with CRC-32 values computed here by a
bit-by-bit CRC-32 (reflected polynomial 0xEDB88320), independent of zlib."""

import struct

import pytest

from drivers.protocol import can_frames as cf
from drivers.protocol import serial_frames as sf
from drivers.protocol.cal_record import crc32_f32, to_f32


def crc32_bitwise(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def xor_hh(body: bytes) -> bytes:
    x = 0
    for c in body:
        x ^= c
    return b"%02X" % x


def test_reference_crc_is_crc32():
    assert crc32_bitwise(b"123456789") == 0xCBF43926  # the CRC-32 check value


THERMAL = (0.5, -1.25, 1.375, -350.0, 0.0, -12.5)  # all exact in float32
SFEM = (1.0, 0.0078125, -0.001953125, 0.0, 0.984375, 0.0, 0.0, 0.0, 1.015625, 0.0125, -0.02, 0.005)


def test_crc_helper_over_float32_le():
    raw = struct.pack("<6f", *THERMAL)
    assert raw[:4] == bytes([0x00, 0x00, 0x00, 0x3F])  # 0.5f little-endian
    assert crc32_f32(THERMAL) == crc32_bitwise(raw)
    # a value that float32 rounds: the CRC is over the float32, not the double
    assert crc32_f32([0.1]) == crc32_bitwise(struct.pack("<f", 0.1)) != crc32_bitwise(struct.pack("<d", 0.1))
    assert crc32_f32([0.1]) == crc32_bitwise(bytes.fromhex("cdcccc3d"))
    assert crc32_f32([-0.0]) == crc32_f32([0.0])  # -0 written as 0


def test_calw_exact_bytes():
    body = b"CALW,0.5,-1.25,1.375,-350,0,-12.5"
    assert sf.cmd_calw(THERMAL[:3], THERMAL[3:]) == b"$" + body + b"*" + xor_hh(body) + b"\n"
    # values that are not exact in float32 are written as the shortest decimal of their float32
    raw = sf.cmd_calw([0.1, -0.7, 1 / 3], [-123.456, 0, -1e-3])
    assert raw.startswith(b"$CALW,0.1,-0.7,0.33333334,-123.456,0,-0.001*")
    vals = [float(x) for x in raw[6:raw.index(b"*")].split(b",")]
    assert struct.pack("<6f", *vals) == struct.pack("<6f", 0.1, -0.7, 1 / 3, -123.456, 0, -1e-3)
    with pytest.raises(ValueError):
        sf.cmd_calw([1, 2], [3, 4, 5])
    with pytest.raises(ValueError):
        sf.cmd_calw([float("nan"), 0, 0], [0, 0, 0])


def test_sfew_calr_sfer_comp_exact_bytes():
    body = b"SFEW,1,0.0078125,-0.001953125,0,0.984375,0,0,0,1.015625,0.0125,-0.02,0.005"
    assert sf.cmd_sfew([SFEM[0:3], SFEM[3:6], SFEM[6:9]], SFEM[9:]) == b"$" + body + b"*" + xor_hh(body) + b"\n"
    assert sf.cmd_calr() == b"$CALR*" + xor_hh(b"CALR") + b"\n"
    assert sf.cmd_sfer() == b"$SFER*" + xor_hh(b"SFER") + b"\n"
    assert sf.cmd_comp(True) == b"$COMP,1*" + xor_hh(b"COMP,1") + b"\n"
    assert sf.cmd_comp(False) == b"$COMP,0*" + xor_hh(b"COMP,0") + b"\n"


def test_board_replies_exact_bytes_and_parse():
    crc = crc32_bitwise(struct.pack("<6f", *THERMAL))
    crc_hex = b"%08X" % crc
    ack = sf.AckFrame("CALW", (sf.fmt_crc(crc),)).encode()
    assert ack == b"$A,CALW," + crc_hex + b"*" + xor_hh(b"A,CALW," + crc_hex) + b"\n"
    body = b"C,0.5,-1.25,1.375,-350,0,-12.5," + crc_hex + b",1"
    c = sf.CalReadFrame(THERMAL, crc, True).encode()
    assert c == b"$" + body + b"*" + xor_hh(body) + b"\n"
    scrc = crc32_bitwise(struct.pack("<12f", *SFEM))
    sbody = b"S," + b",".join(sf.fmt_f32(v).encode() for v in SFEM) + b",%08X" % scrc
    s = sf.SfemReadFrame(SFEM, scrc).encode()
    assert s == b"$" + sbody + b"*" + xor_hh(sbody) + b"\n"
    p = sf.FrameParser()
    frames = p.feed(ack + c + s + sf.AckFrame("COMP").encode() + sf.ErrorFrame("CALW", "flash write failed").encode())
    assert frames == [sf.AckFrame("CALW", (crc_hex.decode(),)), sf.CalReadFrame(THERMAL, crc, True),
                      sf.SfemReadFrame(to_f32(SFEM), scrc), sf.AckFrame("COMP"), sf.ErrorFrame("CALW", "flash write failed")]
    # malformed replies are counted, not fatal
    bad = sf.encode("C,1,2,3,4,5,6,ZZZZZZZZ,1") + sf.encode("C,1,2,3,4,5,6,00000000,2") + sf.encode("S,1,2,3")
    assert p.feed(bad) == [] and p.stats.frames_malformed == 3


def test_board_side_parses_calibration_commands():
    p = sf.FrameParser(board_side=True)
    frames = p.feed(sf.cmd_calw(THERMAL[:3], THERMAL[3:]) + sf.cmd_calr() + sf.cmd_comp(True)
                    + sf.cmd_sfew([SFEM[0:3], SFEM[3:6], SFEM[6:9]], SFEM[9:]) + sf.cmd_sfer()
                    + sf.encode("COMP,2") + sf.encode("CALW,1,2,3") + sf.encode("CALW,1,2,3,4,5,nan"))
    assert [f.command for f in frames] == ["CALW", "CALR", "COMP", "SFEW", "SFER"]
    assert frames[0].args == ("0.5", "-1.25", "1.375", "-350", "0", "-12.5")
    assert frames[2].args == ("1",)
    assert p.stats.frames_malformed == 3


# ---- CAN --------------------------------------------------------------------------------------

def test_can_calibration_commands_exact_bytes():
    assert cf.encode_cal_field(0, 0.5) == bytes([0x05, 0x00, 0x00, 0x00, 0x00, 0x3F])
    assert cf.encode_cal_field(3, -350.0) == bytes([0x05, 0x03]) + struct.pack("<f", -350.0)
    assert struct.pack("<f", -350.0) == bytes([0x00, 0x00, 0xAF, 0xC3])
    crc = crc32_bitwise(struct.pack("<6f", *THERMAL))
    assert cf.encode_cal_commit(crc) == bytes([0x06]) + crc.to_bytes(4, "little")
    assert cf.encode_cal_read() == b"\x07"
    assert cf.encode_comp(True) == b"\x08\x01" and cf.encode_comp(False) == b"\x08\x00"
    with pytest.raises(ValueError):
        cf.encode_cal_field(6, 1.0)
    d = cf.decode_cal_command(cf.encode_cal_field(5, -12.5))
    assert (d.cmd, d.field, d.value) == (0x05, 5, -12.5)
    assert cf.decode_cal_command(cf.encode_cal_commit(crc)).crc == crc
    assert cf.decode_cal_command(b"\x08\x01").on is True
    for bad in (b"\x05\x06\0\0\0\0", b"\x06\x01", b"\x08\x02", b"\x01"):
        with pytest.raises(ValueError):
            cf.decode_cal_command(bad)


def test_can_calibration_replies_exact_bytes():
    crc = crc32_bitwise(struct.pack("<6f", *THERMAL))
    st = cf.encode_cal_status(cf.CAL_STORED, True, crc)
    assert st == bytes([4, 0, 1]) + crc.to_bytes(4, "little") and len(st) == 7
    assert cf.encode_cal_status(cf.CAL_CRC_MISMATCH, False, 0)[:3] == bytes([4, 1, 0])
    assert cf.encode_cal_status(cf.CAL_WRITE_FAILED, False, 0)[:3] == bytes([4, 2, 0])
    for k, v in enumerate(THERMAL):
        assert cf.encode_cal_stored_field(k, v) == bytes([5 + k]) + struct.pack("<f", v)
        assert cf.decode_cal_reply(cf.encode_cal_stored_field(k, v)) == (5 + k, v)
    idx, status = cf.decode_cal_reply(st)
    assert idx == 4 and status == cf.CalStatus(0, True, crc) and status.text == "stored"
    assert cf.is_cal_reply(st) and not cf.is_cal_reply(b"\x03" + bytes(4))
    with pytest.raises(ValueError):
        cf.decode_cal_reply(b"\x04\x00\x01")
    with pytest.raises(ValueError):
        cf.decode_cal_reply(b"\x0b" + bytes(4))
