"""Logs are looked at before any science (issue 22).

Measured on main before: `station calibrate` on a log with m/s2 in the g columns gave TDB x9.8 with
exit 0; Kelvin temperatures, an all-zero clock, reversed or duplicated rows all gave a result;
`# odr_hz: 1e9` made `station replay --logs` spin forever, 0/nan/inf/-5 a traceback; a 200 MB log
took 1.9 GB. Now each is one line on stderr and exit 2, from the reader every command shares
(contracts/logfile.py read_log -> LogChecker; cli/commands/log_import.py for other tools' logs).
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cli import main as cli
from contracts import logfile as lf
from contracts.logfile import DutLog, format_log, parse_log, read_log, write_log
from station.science.thermal_calibration import calibrate
from contracts.types import StationError
from thermal_synth import fast_thermal

ROOT = Path(__file__).resolve().parents[1]
TRUTH = dict(tdb_mg_per_c=(0.47, 0.07, -0.2), tdsf_ppm_per_c=(-125.0, -38.0, -58.0))
META = {"serial": "SYN0001", "sensor": "LIS3DSH", "odr_hz": "3.125"}


@pytest.fixture(scope="module")
def rec():
    return fast_thermal(seed=8, **TRUTH)


def _dut(rec, **kw) -> DutLog:
    d = dict(time_s=rec.time_s.copy(), acc_g=rec.acc_g.copy(), temp_c=rec.temp_c.copy(), meta=dict(META),
             position=rec.position.astype(np.int64))
    d.update(kw)
    return DutLog(**d)


@pytest.fixture(scope="module")
def logs(rec, tmp_path_factory):
    """Every bad log of the issue, written as files (design 5.1), in one folder."""
    d = tmp_path_factory.mktemp("bad")
    write_log(d / "good.csv", _dut(rec))
    write_log(d / "ms2.csv", _dut(rec, acc_g=rec.acc_g * 9.80665))
    write_log(d / "mg.csv", _dut(rec, acc_g=rec.acc_g * 1000.0))
    write_log(d / "counts.csv", _dut(rec, acc_g=np.round(rec.acc_g * 16384.0)))
    write_log(d / "kelvin.csv", _dut(rec, temp_c=rec.temp_c + 273.15))
    write_log(d / "zero_time.csv", _dut(rec, time_s=np.zeros_like(rec.time_s)))
    lines = format_log(_dut(rec)).splitlines()
    h = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))  # header row index (line h + 1)
    rows = lines[h + 1:]
    (d / "reversed.csv").write_text("\n".join(lines[:h + 1] + rows[::-1]) + "\n")
    (d / "duplicated.csv").write_text("\n".join(lines[:h + 1] + rows[:100] + [rows[99]] + rows[100:]) + "\n")
    for name, value in (("odr_1e9", "1e9"), ("odr_0", "0"), ("odr_nan", "nan"), ("odr_inf", "inf"),
                        ("odr_neg", "-5"), ("odr_text", "fast"), ("odr_wrong", "100")):
        write_log(d / f"{name}.csv", _dut(rec, meta={**META, "odr_hz": value}))
    write_log(d / "ug_text.csv", _dut(rec, meta={**META, "ug_per_lsb": "sixty"}))
    write_log(d / "lost_neg.csv", _dut(rec, meta={**META, "lost_samples": "-3"}))
    return d


ODR_RULE = "(0 < odr_hz <= 100000 Hz)"
BAD = [
    ("ms2.csv", "ms2.csv: ax_g/ay_g/az_g look like m/s2, not g (median |a| = 10.1): give --accel-units m/s2"),
    ("mg.csv", "mg.csv: ax_g/ay_g/az_g look like mg, not g (median |a| = 1031): give --accel-units mg"),
    ("counts.csv", "counts.csv: ax_g/ay_g/az_g look like raw counts, not g (median |a| = 16900): give --accel-units "
                   "counts --counts-per-g N (N = the sensor's LSB per g, about 16900 here)"),
    ("kelvin.csv", "kelvin.csv: temp_c looks like kelvin, not C (median 312.15): give --temp-units K"),
    ("zero_time.csv", "zero_time.csv: time_s is 0.0 in every row: the log has no sample times"),
    ("reversed.csv", "reversed.csv: line 6: time_s = 6911.865 goes back from 6912.185 on line 5 (rows out of order?): "
                     "sample times must increase"),
    ("duplicated.csv", "duplicated.csv: line 105: time_s = 44.025 repeats line 104 (a duplicated row?): "
                       "sample times must increase"),
    ("odr_1e9.csv", f"odr_1e9.csv: header '# odr_hz: 1e9' is out of range {ODR_RULE}"),
    ("odr_0.csv", f"odr_0.csv: header '# odr_hz: 0' is out of range {ODR_RULE}"),
    ("odr_nan.csv", f"odr_nan.csv: header '# odr_hz: nan' is not a finite number {ODR_RULE}"),
    ("odr_inf.csv", f"odr_inf.csv: header '# odr_hz: inf' is not a finite number {ODR_RULE}"),
    ("odr_neg.csv", f"odr_neg.csv: header '# odr_hz: -5' is out of range {ODR_RULE}"),
    ("odr_text.csv", f"odr_text.csv: header '# odr_hz: fast' is not a number {ODR_RULE}"),
    ("odr_wrong.csv", "odr_wrong.csv: header '# odr_hz: 100' does not match the sample times "
                      "(median interval 0.32 s, 3.125 Hz)"),
    ("ug_text.csv", "ug_text.csv: header '# ug_per_lsb: sixty' is not a number (0 < ug_per_lsb <= 100000)"),
    ("lost_neg.csv", "lost_neg.csv: header '# lost_samples: -3' is out of range (an integer >= 0)"),
]


def _err(capsys, *argv) -> tuple[int, list[str], str]:
    code = cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, [ln for ln in out.err.splitlines() if ln.strip()], out.out


@pytest.mark.parametrize("name,line", BAD, ids=[b[0] for b in BAD])
def test_each_bad_log_is_one_exact_line_and_exit_2(logs, name, line, capsys, monkeypatch):
    monkeypatch.chdir(logs)
    code, err, out = _err(capsys, "calibrate", name, "--json")
    assert (code, err, out) == (2, [f"station calibrate: error: {line}"], "")


@pytest.mark.parametrize("name", ["ms2.csv", "kelvin.csv", "reversed.csv", "odr_1e9.csv"])
def test_sfem_and_diagnose_read_through_the_same_checks(logs, name, capsys, monkeypatch):
    monkeypatch.chdir(logs)
    line = dict(BAD)[name]
    for cmd in ("sfem", "diagnose"):
        code, err, _ = _err(capsys, cmd, name, *(["--norm-only"] if cmd == "sfem" else []))
        assert (code, err) == (2, [f"station {cmd}: error: {line}"])


def test_subprocess_no_traceback_and_exit_2(logs):
    for name in ("ms2.csv", "odr_nan.csv"):
        out = subprocess.run([sys.executable, "-m", "cli", "calibrate", name], capture_output=True, text=True,
                             timeout=120, cwd=logs)
        assert out.returncode == 2 and out.stdout == "" and "Traceback" not in out.stderr
        assert out.stderr.splitlines() == [f"station calibrate: error: {dict(BAD)[name]}"]


def test_replay_of_logs_refuses_a_bad_header_before_it_starts(logs):
    """station replay --logs reads the logs with read_log: odr_hz 1e9 spun forever, 0 gave a traceback."""
    from station.replay.recording import from_logs

    for name in ("odr_1e9.csv", "odr_0.csv", "odr_nan.csv", "odr_inf.csv", "odr_neg.csv", "zero_time.csv"):
        with pytest.raises(StationError) as err:
            from_logs([logs / name], profile="fast-thermal", compare=False)
        assert str(err.value) == str(logs / dict(BAD)[name])


def test_the_converting_options_give_the_good_logs_result(logs, capsys, monkeypatch):
    """The option each error names converts the log: the same coefficients as the g/C log."""
    monkeypatch.chdir(logs)
    assert cli.main(["calibrate", "good.csv", "--json"]) == 0
    good = json.loads(capsys.readouterr().out)["axes"]
    for args in (("ms2.csv", "--accel-units", "m/s2"), ("mg.csv", "--accel-units", "mg"),
                 ("kelvin.csv", "--temp-units", "K"), ("counts.csv", "--accel-units", "counts", "--counts-per-g", "16384")):
        assert cli.main(["calibrate", *args, "--json"]) == 0, args
        got = json.loads(capsys.readouterr().out)["axes"]
        tol = 2e-3 if "counts" in args else 1e-6  # counts were rounded to 1/16384 g
        for ax in "xyz":
            assert got[ax]["tdb_mg_per_c"] == pytest.approx(good[ax]["tdb_mg_per_c"], abs=tol), (args, ax)
    # the wrong option is named too
    code, err, _ = _err(capsys, "calibrate", "good.csv", "--accel-units", "m/s2")
    assert (code, err) == (2, ["station calibrate: error: good.csv: ax_g/ay_g/az_g look like g, not m/s2 "
                               "(median |a| = 1.03): drop --accel-units m/s2"])
    code, err, _ = _err(capsys, "calibrate", "counts.csv", "--accel-units", "counts", "--counts-per-g", "1000")
    assert (code, err) == (2, ["station calibrate: error: counts.csv: ax_g/ay_g/az_g with --counts-per-g 1000 give "
                               "median |a| = 16.9 g, not about 1 g: check --counts-per-g (these read about 16900 per g)"])
    code, err, _ = _err(capsys, "calibrate", "good.csv", "--temp-units", "K")
    assert (code, err) == (2, ["station calibrate: error: good.csv: temp_c looks like C, not kelvin (median 39.00): "
                               "drop --temp-units K"])


def test_a_good_log_gives_the_same_result_as_before(rec, logs, capsys):
    """The science on the file equals the science on the samples (at stored precision), and the
    reader gives the numbers np.loadtxt of the whole text gave (the reader before issue 22)."""
    path = logs / "good.csv"
    assert cli.main(["calibrate", str(path), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    stored = _dut(rec, time_s=np.round(rec.time_s, 6), acc_g=np.round(rec.acc_g, 7), temp_c=np.round(rec.temp_c, 4))
    assert got == json.loads(json.dumps(calibrate(stored)))
    text = path.read_text()
    old = np.loadtxt([ln for ln in text.splitlines() if ln and not ln.startswith("#")][1:], delimiter=",", ndmin=2)
    log = read_log(path)
    np.testing.assert_array_equal(log.time_s, old[:, 0])
    np.testing.assert_array_equal(log.acc_g, old[:, 1:4])
    np.testing.assert_array_equal(log.temp_c, old[:, 4])
    np.testing.assert_array_equal(log.position, old[:, 5].astype(np.int64))


def test_chunks_do_not_change_values_or_line_numbers(logs, monkeypatch):
    """Read a few hundred bytes at a time (every row boundary case), with comment and blank lines
    and CRLF endings inside: the same arrays, and an error deep in the file names its real line."""
    text = (logs / "good.csv").read_text()
    lines = text.splitlines()
    lines.insert(500, "# a note in the middle")
    lines.insert(800, "")
    crlf = "\r\n".join(lines) + "\r\n"
    p = logs.parent / "chunks.csv"
    p.write_bytes(crlf.encode())
    whole = read_log(p)
    monkeypatch.setattr(lf, "CHUNK_BYTES", 333)
    small = read_log(p)
    for a, b in ((whole.time_s, small.time_s), (whole.acc_g, small.acc_g), (whole.temp_c, small.temp_c),
                 (whole.position, small.position)):
        np.testing.assert_array_equal(a, b)
    assert whole.meta == small.meta == META
    assert len(whole) == len(read_log(logs / "good.csv"))
    # a duplicate at file line 3001 (after the two inserted lines)
    lines[3000] = lines[2999]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(StationError, match=r": line 3001: time_s = [0-9.]+ repeats line 3000 "):
        read_log(p)
    with pytest.raises(StationError, match=r": line 3001: time_s = [0-9.]+ repeats line 3000 "):
        parse_log(p.read_text(), str(p))


@pytest.mark.parametrize("text,needle", [
    ("0,0,0,1,25\n0.5,0,0,1,25\n1.0,0,0,1,-80\n", "line 4: temp_c = -80.0 is outside -60..150 C"),
    ("0,0,0,1,25\n0.5,0,0,1,25\n1.0,0,0,1,151\n", "line 4: temp_c = 151.0 is outside -60..150 C"),
    ("0,0,0,0.01,25\n0.5,0,0,0.01,25\n", "ax_g/ay_g/az_g do not look like g (median |a| = 0.01; a DUT at rest reads about 1 g)"),
    ("0,0,0,1,25\n0.5,0,0,1,25\n0.25,0,0,1,25\n", "line 4: time_s = 0.25 goes back from 0.5 on line 3"),
    ("0,0,0,1,25\n0,0,0,1,25\n", "time_s is 0.0 in every row"),
    ("0,0,0,1,25\n0.5,0,0,1\n", "line 3: malformed data row (4 fields, the header has 5)"),
])
def test_parse_log_names_the_problem(text, needle):
    with pytest.raises(StationError) as err:
        parse_log("time_s,ax_g,ay_g,az_g,temp_c\n" + text, "x.csv")
    assert str(err.value).startswith("x.csv: ") and needle in str(err.value)


def test_check_log_on_a_log_in_memory(rec):
    lf.check_log(_dut(rec), "mem")
    with pytest.raises(StationError, match=r"^mem: row 2: time_s = 0.0 repeats row 1"):
        lf.check_log(_dut(rec, time_s=np.concatenate([[0.0, 0.0], rec.time_s[2:] + 1])), "mem")
    with pytest.raises(StationError, match="look like m/s2"):
        lf.check_log(_dut(rec, acc_g=rec.acc_g * 9.81), "mem")
    t = rec.temp_c + 273.15
    with pytest.raises(StationError, match="looks like kelvin"):
        lf.check_log(_dut(rec, temp_c=t), "mem")
    assert np.array_equal(t, rec.temp_c + 273.15)  # the caller's arrays are not touched


@pytest.mark.parametrize("median,unit", [(1.0, "g"), (0.98, "g"), (9.81, "m/s2"), (1000.0, "mg"), (16384.0, "counts"),
                                         (2048.0, "counts"), (256410.0, "counts"), (1.0 / 0.061e-3, "counts"),
                                         (0.01, None), (30.0, None)])
def test_unit_guess(median, unit):
    assert lf.guess_accel_units(median) == unit


def test_memory_stays_about_the_arrays(tmp_path):
    """A 43 MB log: the reader before kept the text, a list of lines, their join and loadtxt's
    copy (peak +430 MB); now the peak grows by about the arrays (49 bytes per row here, +50 MB)."""
    n = 800_000
    t = np.arange(n) / 100.0
    acc = np.tile([0.577, 0.577, 0.577], (n, 1)) + np.sin(t)[:, None] * 1e-3
    p = tmp_path / "big.csv"
    with open(p, "w") as f:
        f.write("# serial: BIG\n# odr_hz: 100\ntime_s,ax_g,ay_g,az_g,temp_c,lamp,position\n")
        np.savetxt(f, np.column_stack([t, acc, 25 + 20 * np.sin(t / 1000), np.zeros(n), np.zeros(n)]),
                   fmt=["%.6f", "%.7f", "%.7f", "%.7f", "%.4f", "%d", "%d"], delimiter=",")
    size_mb = p.stat().st_size / 1e6
    # VmHWM (peak RSS of this process image): ru_maxrss of a child carries its parent's (pytest's) peak
    code = textwrap.dedent(f"""
        def hwm():
            for ln in open("/proc/self/status"):
                if ln.startswith("VmHWM"):
                    return int(ln.split()[1]) / 1024
        from contracts.logfile import read_log
        before = hwm()
        log = read_log({str(p)!r})
        print(len(log), hwm() - before)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    rows, grew_mb = out.stdout.split()
    arrays_mb = n * 49 / 1e6
    assert int(rows) == n
    print(f"{size_mb:.0f} MB log: peak grew by {float(grew_mb):.0f} MB (arrays {arrays_mb:.0f} MB)")
    assert float(grew_mb) < 2.0 * arrays_mb, (grew_mb, arrays_mb)  # before: ~11x (430 MB here)


def test_replay_of_logs_refuses_a_serial_the_station_would_refuse(rec, tmp_path):
    """A log's serial (its `# serial:` or its file name) becomes the replayed board's identity: one
    the station's identity rules refuse (design 3.1: empty, over 32 characters, not a serial) is a
    clear error before the replay starts, not a batch whose only board is stopped."""
    from station.replay.recording import from_logs

    for serial, words in (("my log 1", "not a serial"), ("X" * 40, "40-character serial")):
        write_log(tmp_path / "a.csv", _dut(rec, meta={**META, "serial": serial}))
        with pytest.raises(StationError) as err:
            from_logs([tmp_path / "a.csv"], profile="fast-thermal", compare=False)
        assert words in str(err.value) and "# serial:" in str(err.value), str(err.value)
    write_log(tmp_path / "a.csv", _dut(rec, meta={**META, "serial": "LOG-0001"}))
    assert from_logs([tmp_path / "a.csv"], profile="fast-thermal", compare=False).duts[0].serial == "LOG-0001"
