"""CAN frame codec (design 3.2): exact payload bytes by node id."""

import struct

import pytest

from drivers.protocol import can_frames as cf


def test_sample_payload_little_endian():
    data = cf.encode_sample(1, -2, 16384, -3, 258)
    assert data == bytes([0x01, 0x00, 0xFE, 0xFF, 0x00, 0x40, 0xFD, 0x02])
    s = cf.decode_sample(data)
    assert (s.ax, s.ay, s.az, s.t, s.seq) == (1, -2, 16384, -3, 2)
    with pytest.raises(ValueError):
        cf.decode_sample(data[:7])


def test_commands():
    assert cf.encode_command(cf.CMD_START) == b"\x01"
    assert cf.encode_command(cf.CMD_STOP) == b"\x02"
    assert cf.encode_command(cf.CMD_IDENTIFY) == b"\x03"
    assert cf.encode_command(cf.CMD_SET_ODR, 12.5) == b"\x04" + struct.pack("<f", 12.5)
    assert cf.decode_command(b"\x04" + struct.pack("<f", 12.5)) == (4, 12.5)
    with pytest.raises(ValueError):
        cf.check_node(0)
    assert cf.split_id(0x185) == (0x180, 5) and cf.split_id(0x67F) == (0x600, 127)


def test_identity_four_frames_any_order():
    frames = cf.encode_identity("ABCDEFGHIJKL", 60.0, 3.125)
    assert frames[0] == b"\x00ABCDEFG" and frames[1] == b"\x01HIJKL\x00\x00"
    assert frames[2] == b"\x02" + struct.pack("<f", 60.0)
    assert frames[3] == b"\x03" + struct.pack("<f", 3.125)
    a = cf.IdentityAssembler()
    assert not a.feed(frames[3]) and not a.feed(frames[1]) and not a.feed(frames[2])
    assert a.feed(frames[0])
    assert (a.serial, a.ug_per_lsb, a.odr_hz) == ("ABCDEFGHIJKL", 60.0, 3.125)
    with pytest.raises(ValueError):
        cf.encode_identity("X" * 15, 60, 1)
    with pytest.raises(ValueError):
        cf.IdentityAssembler().feed(b"\x07")


def test_slcan_lines_split_in_bulk_exactly():
    """drivers/protocol/slcan_lines.py: the bulk reader's parser (issue 15), byte for byte."""
    from drivers.protocol.slcan_lines import MAX_LINE, split_frames

    buf = bytearray(b"\rz\rt5818010203040506070A\rt58120102\x07t1230\rt58120102ABCD\rT1234567810\rt12\rt18\xff\xfe\rt5")
    frames, garbled = split_frames(buf)
    assert frames == [(0x581, bytes([1, 2, 3, 4, 5, 6, 7, 0x0A])), (0x123, b""),
                      (0x581, b"\x01\x02")]  # the last with a 4-digit adapter timestamp
    # garbled: a line ended by the error bell, "t12", "t18\xff\xfe"; the partial line waits
    assert garbled == 3 and buf == bytearray(b"t5")
    buf += b"8120304\r"
    assert split_frames(buf) == ([(0x581, b"\x03\x04")], 0) and buf == bytearray()
    buf += b"x" * (MAX_LINE + 10)  # noise without a line end does not grow without bound
    assert split_frames(buf) == ([], 1) and len(buf) == MAX_LINE
