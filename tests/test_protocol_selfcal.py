"""The on-board self-calibration frames (design 3.1): decoded by the station, malformed ones counted."""

from drivers.protocol import serial_frames as sf
from drivers.protocol.selfcal_frames import SegmentReportFrame, SelfCalResultFrame


def test_segment_and_result_frames_decode_and_bad_ones_are_counted():
    p = sf.FrameParser()
    frames = p.feed(sf.encode("G,3,1,123456789,0.57735,-0.5773,0.577,61.25,1000")
                    + sf.encode("R,0.5,-1.25,0.031,-120,0,-480.5,6,2")
                    + sf.encode("G,3,1,5,nan,0,0,25,1000")  # non-finite: malformed
                    + sf.encode("R,1,2,3")  # short: malformed
                    + sf.encode("G,-1,0,5,0,0,0,25,1000"))  # negative index: malformed
    assert frames == [
        SegmentReportFrame(3, 1, 123456789, (0.57735, -0.5773, 0.577), 61.25, 1000),
        SelfCalResultFrame((0.5, -1.25, 0.031), (-120.0, 0.0, -480.5), 6, 2),
    ]
    assert p.stats.frames_ok == 2 and p.stats.frames_malformed == 3


def test_board_side_parses_scal_and_scrr():
    p = sf.FrameParser(board_side=True)
    got = p.feed(sf.cmd_scal(True) + sf.cmd_scal(False) + sf.cmd_scrr() + sf.encode("SCAL,2") + sf.encode("SCRR,1"))
    assert got == [sf.CommandFrame("SCAL", ("1",)), sf.CommandFrame("SCAL", ("0",)), sf.CommandFrame("SCRR")]
    assert p.stats.frames_malformed == 2
