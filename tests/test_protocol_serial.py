"""Serial frame codec (design 3.1): exact bytes, checksums, and a parser that survives bad lines."""

from drivers.base import LinkStats
from drivers.protocol import serial_frames as sf
from contracts.types import Identity


def test_station_commands_exact_bytes():
    # XOR by hand: I^D = 0x49^0x44 = 0x0D; S^T^A^R^T = 0x40; S^T^O^P = 0x18
    assert sf.cmd_id() == b"$ID*0D\n"
    assert sf.cmd_start() == b"$START*40\n"
    assert sf.cmd_stop() == b"$STOP*18\n"
    body = b"ODR,50"
    x = 0
    for c in body:
        x ^= c
    assert sf.cmd_odr(50) == b"$ODR,50*%02X\n" % x
    assert sf.cmd_odr(3.125) .startswith(b"$ODR,3.125*")


def test_checksum_upper_case_hex_and_sample_round_trip():
    raw = sf.SampleFrame(7, 1000000, -1, 2, 16384, 3).encode()
    assert raw.startswith(b"$D,7,1000000,-1,2,16384,3*") and raw.endswith(b"\n")
    hh = raw[-3:-1]
    assert hh == hh.upper() and int(hh, 16) == sf.checksum(b"D,7,1000000,-1,2,16384,3")
    assert sf.FrameParser().feed(raw) == [sf.SampleFrame(7, 1000000, -1, 2, 16384, 3)]


def test_identity_frame_fields():
    ident = Identity("SN42", "ADXL355", "2.1", 3.9, -9.05, 1885, 3.125)
    raw = sf.IdentityFrame(ident).encode()
    assert raw.startswith(b"$I,SN42,ADXL355,2.1,3.9,-9.05,1885,3.125*")
    (frame,) = sf.FrameParser().feed(raw)
    assert frame.identity == ident


def test_ack_and_error_frames_counted():
    stats = LinkStats()
    p = sf.FrameParser(stats)
    out = p.feed(sf.encode("A,START") + sf.encode("E,42,sensor not responding, retry"))
    assert out == [sf.AckFrame("START"), sf.ErrorFrame("42", "sensor not responding, retry")]
    assert stats.errors_reported == 1 and stats.frames_ok == 2


def test_split_reads_byte_by_byte():
    raw = b"".join(sf.SampleFrame(i, i * 320000, i, -i, 1000 + i, 5).encode() for i in range(5))
    p = sf.FrameParser()
    got = []
    for k in range(len(raw)):
        got += p.feed(raw[k : k + 1])
    assert [f.seq for f in got] == [0, 1, 2, 3, 4]
    assert p.stats.frames_ok == 5 and p.stats.bytes_skipped == 0


def test_garbage_bad_checksum_unknown_type_short_line():
    stats = LinkStats()
    p = sf.FrameParser(stats)
    good = sf.SampleFrame(1, 10, 1, 2, 3, 4).encode()
    bad_ck = good[:-3] + b"00\n" if not good.endswith(b"*00\n") else good[:-3] + b"01\n"
    data = (
        b"\x00\xffnoise"  # garbage before a frame on the same line: 7 bytes skipped
        + good
        + b"garbage line\n"  # whole line of garbage: 13 bytes incl. newline
        + bad_ck
        + sf.encode("X,1,2")  # unknown type
        + sf.encode("D,1,2,3")  # short line
        + sf.encode("D,1,2,3,4,5,zz")  # unparsable field
        + b"$D,1,2*4\n"  # malformed checksum field
        + b"\r\n"
        + sf.SampleFrame(2, 20, 1, 2, 3, 4).encode().replace(b"\n", b"\r\n")  # CRLF tolerated
    )
    frames = p.feed(data)
    assert [f.seq for f in frames] == [1, 2]
    assert stats.frames_ok == 2
    assert stats.frames_bad_checksum == 1
    assert stats.frames_malformed == 4
    assert stats.bytes_skipped == 7 + 13 + 1


def test_long_run_without_newline_is_dropped_but_next_frame_survives():
    p = sf.FrameParser()
    p.feed(b"x" * 2000)
    assert p.stats.bytes_skipped == 2000
    assert len(p.feed(sf.SampleFrame(3, 1, 1, 1, 1, 1).encode())) == 1


def test_seq_tracker_gaps_and_uint32_wrap():
    s = sf.SeqTracker(32)
    lost = [s.update(q) for q in (10, 11, 14, 15)]
    assert lost == [0, 0, 2, 0] and s.lost == 2
    s = sf.SeqTracker(32)
    lost = [s.update(q) for q in (0xFFFFFFFE, 0xFFFFFFFF, 0, 3)]
    assert lost == [0, 0, 0, 2] and s.lost == 2
    assert s.index == 0xFFFFFFFE + 5
    s = sf.SeqTracker(8)
    lost = [s.update(q) for q in (250, 255, 1, 2)]
    assert lost == [0, 4, 1, 0]
    assert s.index == 250 + 8


def test_seq_backwards_is_resync_not_loss():
    s = sf.SeqTracker(32)
    for q in (100, 101, 5, 6):
        s.update(q)
    assert s.lost == 0 and s.resyncs == 1


def test_clock_unwrapper_uint32_wrap():
    u = sf.ClockUnwrapper()
    t = [u.update(v) for v in (2**32 - 640000, 2**32 - 320000, 0, 320000)]
    assert t == [2**32 - 640000, 2**32 - 320000, 2**32, 2**32 + 320000]
    u = sf.ClockUnwrapper()  # a 64-bit clock passes through
    assert [u.update(v) for v in (2**40, 2**40 + 5)] == [2**40, 2**40 + 5]


def test_one_corrupt_clock_value_is_an_outlier_not_a_wrap():
    """t_us = 0xFFFFFFFF between two samples 20 ms apart once counted as a 32-bit wrap and moved
    the rest of that DUT's run 4,295 s later."""
    u = sf.ClockUnwrapper()
    got = [u.update(v) for v in (1_000_000, 1_020_000, 0xFFFFFFFF, 1_060_000, 1_080_000)]
    assert got == [1_000_000, 1_020_000, None, 1_060_000, 1_080_000]  # the outlier's period counts
    assert u.offset == 0 and u.outliers == 1 and u.jumps == 0


def test_a_wrap_with_lost_samples_is_still_a_wrap():
    u = sf.ClockUnwrapper()
    assert u.update(2**32 - 640_000) == 2**32 - 640_000
    assert u.update(2**32 - 320_000) == 2**32 - 320_000
    assert u.update(640_000, steps=3) == 2**32 + 640_000  # two samples lost across the wrap
    assert u.update(0xFFFFFFFF) is None  # an outlier right after the wrap is not a second wrap
    assert u.update(1_280_000) == 2**32 + 1_280_000 and u.offset == 2**32


def test_a_real_clock_jump_costs_one_sample_then_the_new_timeline_is_taken():
    u = sf.ClockUnwrapper()
    got = [u.update(v) for v in (5_000_000, 5_020_000, 300_000, 320_000, 340_000)]  # board reset
    assert got == [5_000_000, 5_020_000, None, 320_000, 340_000]  # 300_000: dropped as an outlier
    assert u.jumps == 1 and u.offset == 0
    u.reset_period()  # ODR changed from 50 Hz to 10 Hz: the first new step is taken as the period
    assert [u.update(v) for v in (440_000, 540_000, 640_000)] == [440_000, 540_000, 640_000]


def test_board_side_parser_reads_commands():
    p = sf.FrameParser(board_side=True)
    frames = p.feed(sf.cmd_id() + sf.cmd_odr(6.25) + sf.cmd_start() + sf.encode("BOGUS"))
    assert frames == [sf.CommandFrame("ID"), sf.CommandFrame("ODR", ("6.25",)), sf.CommandFrame("START")]
    assert p.stats.frames_malformed == 1
