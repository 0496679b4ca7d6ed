"""The design 5.1 log format: what the station writes it reads back, and user mistakes are one line."""

import numpy as np
import pytest

from contracts.logfile import DutLog, format_log, parse_log, read_log, write_log
from contracts.types import StationError


def _log(n: int = 50) -> DutLog:
    rng = np.random.default_rng(1)
    acc = np.round(rng.integers(-30000, 30000, size=(n, 3)) * 60e-6, 7)
    return DutLog(
        time_s=np.round(np.arange(n) / 3.125, 6),
        acc_g=acc,
        temp_c=np.round(25 + rng.integers(-5, 30, size=n).astype(float), 4),
        meta={"serial": "SIM0001", "sensor": "LIS3DSH", "profile": "fast-thermal"},
        lamp=(np.arange(n) > 20).astype(np.int8),
        position=np.where(np.arange(n) > 30, 1, 0),
        ref_dir=np.tile([0.57735, 0.57735, 0.57735], (n, 1)),
    )


def test_round_trip_is_exact_at_stored_precision(tmp_path):
    log = _log()
    path = tmp_path / "SIM0001.csv"
    write_log(path, log)
    back = read_log(path)
    assert back.meta == log.meta
    assert back.serial == "SIM0001"
    np.testing.assert_array_equal(back.time_s, log.time_s)
    np.testing.assert_array_equal(back.acc_g, log.acc_g)
    np.testing.assert_array_equal(back.temp_c, log.temp_c)
    np.testing.assert_array_equal(back.lamp, log.lamp)
    np.testing.assert_array_equal(back.position, log.position)
    np.testing.assert_allclose(back.ref_dir, log.ref_dir)
    assert format_log(back) == format_log(log)


def test_required_columns_only():
    text = "time_s,ax_g,ay_g,az_g,temp_c\n0,0.1,0.2,0.3,25\n0.32,0.1,0.2,0.3,26\n"
    log = parse_log(text)
    assert len(log) == 2 and log.lamp is None and log.ref_dir is None
    assert log.block().acc_g.shape == (2, 3)


def test_missing_file_is_one_clear_error(tmp_path):
    with pytest.raises(StationError, match="no such file"):
        read_log(tmp_path / "nope.csv")


def test_missing_column_names_the_column():
    with pytest.raises(StationError, match="missing column.*temp_c"):
        parse_log("time_s,ax_g,ay_g,az_g\n0,0,0,1\n")


def test_malformed_row_is_reported():
    with pytest.raises(StationError, match="malformed"):
        parse_log("time_s,ax_g,ay_g,az_g,temp_c\n0,0,0,1,abc\n")


def test_no_header():
    with pytest.raises(StationError, match="no header"):
        parse_log("# serial: X\n")


@pytest.mark.parametrize("row,needle", [
    ("0,0,0,1,25,1e300,0", "line 4: lamp = 1e+300 must be 0 or 1"),
    ("0,0,0,1,25,1,1e300", "line 4: position = 1e+300 must be an integer"),
    ("0,0,0,1,25,1,2.5", "line 4: position = 2.5"),
    ("0,nan,0,1,25,1,0", "line 4: ax_g = nan is not a finite number"),
    ("0,0,0,1,inf,1,0", "line 4: temp_c = inf is not a finite number"),
    ("-inf,0,0,1,25,1,0", "line 4: time_s = -inf"),
])
def test_non_finite_samples_and_out_of_range_lamp_or_position_name_the_line(row, needle):
    """Issue 10: these were accepted (NaN/inf samples) or silently cast to int64 min."""
    text = "# serial: X\ntime_s,ax_g,ay_g,az_g,temp_c,lamp,position\n0,0,0,1,25,0,-1\n" + row + "\n1,0,0,1,25,1,5\n"
    with pytest.raises(StationError) as err:
        parse_log(text, "bad.csv")
    assert str(err.value).startswith("bad.csv: ") and needle in str(err.value)


def test_unknown_position_and_both_lamp_states_are_accepted():
    log = parse_log("time_s,ax_g,ay_g,az_g,temp_c,lamp,position\n0,0,0,1,25,0,-1\n1,0,0,1,25,1,5\n")
    assert log.position.tolist() == [-1, 5] and log.lamp.tolist() == [0, 1]
