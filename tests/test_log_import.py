"""Bring your own log (issue 11): delimited text from other tools, with a column map and units.

Truth: a simulated log written by hand in another tool's shape (tab separated, m/s^2, timestamps in
ms, its own column names; or semicolons and raw counts) must read back to the same samples, and
`station diagnose` must give the same result on it as on the station's own CSV.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import diag_helpers as H
from cli.commands.log_import import G0_M_S2, import_log, parse_import
from contracts.logfile import write_log
from contracts.types import StationError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sweep_log():
    logs, truths = H.sim_logs(("bias_t2",), profile=H.SWEEP[:3], seed=7, noise="realistic", odr_hz=1.0)
    return logs[0]


def _tsv(log, path: Path) -> Path:
    lines = ["# serial: EXT42", "timestamp\tacc_x\tacc_y\tacc_z\ttemperature\tgyro_x"]
    t0_ms = 1_700_000_000_000.0
    for t, a, T in zip(log.time_s, log.acc_g, log.temp_c):
        lines.append(f"{t0_ms + t * 1000:.3f}\t{a[0] * G0_M_S2:.7f}\t{a[1] * G0_M_S2:.7f}\t{a[2] * G0_M_S2:.7f}\t{T:.3f}\t0.01")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_tsv_in_m_s2_with_ms_timestamps_reads_back(sweep_log, tmp_path):
    p = _tsv(sweep_log, tmp_path / "ext.tsv")
    got = import_log(p, columns="time=timestamp,ax=acc_x,ay=acc_y,az=acc_z,temp=temperature",
                     accel_units="m/s2", time_units="ms")
    assert got.serial == "EXT42"
    np.testing.assert_allclose(got.time_s, sweep_log.time_s - sweep_log.time_s[0], atol=2e-6)
    np.testing.assert_allclose(got.acc_g, sweep_log.acc_g, atol=1e-7)
    np.testing.assert_allclose(got.temp_c, sweep_log.temp_c, atol=1e-3)
    # the column names are common ones: recognised without a map
    auto = import_log(p, accel_units="m/s2", time_units="ms")
    np.testing.assert_allclose(auto.acc_g, got.acc_g)


def test_semicolons_and_counts():
    text = "t;x;y;z;temp_c\n0;100;-50;16384;20.5\n0.5;101;-49;16383;20.6\n"
    log = parse_import(text, accel_units="counts", counts_per_g=16384.0)
    assert log.acc_g[0].tolist() == pytest.approx([100 / 16384, -50 / 16384, 1.0])
    assert log.time_s.tolist() == [0.0, 0.5]
    with pytest.raises(StationError, match="counts-per-g"):
        parse_import(text, accel_units="counts")
    with pytest.raises(StationError, match="cannot find column"):
        parse_import("a,b,c\n1,2,3\n")
    with pytest.raises(StationError, match="no column 'nope'"):
        parse_import(text, columns="temp=nope")


def test_diagnose_cli_on_an_imported_log_matches_the_station_csv(sweep_log, tmp_path):
    ext = _tsv(sweep_log, tmp_path / "ext.tsv")
    own = tmp_path / "own.csv"
    write_log(own, sweep_log)
    args = ["--candidates", "bias_t2,hysteresis", "--json"]
    a = subprocess.run([sys.executable, "-m", "cli", "diagnose", own, *args], capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    b = subprocess.run([sys.executable, "-m", "cli", "diagnose", ext, *args, "--accel-units", "m/s2",
                        "--time-units", "ms", "--columns", "time=timestamp,temp=temperature"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert a.returncode == 0, a.stderr
    assert b.returncode == 0, b.stderr
    da, db = json.loads(a.stdout), json.loads(b.stdout)
    assert db["serials"] == ["EXT42"]
    assert da["admitted"] == db["admitted"] == ["bias_t2"]
    assert db["baseline"]["heldout_rms_mg"] == pytest.approx(da["baseline"]["heldout_rms_mg"], rel=1e-3)


# ---- issue 22: an imported log is looked at before any science, like a station log -----------------
def test_other_units_are_named_with_the_option_that_converts_them(sweep_log, tmp_path, capsys):
    """The TSV above is in m/s2: read as g (no --accel-units) it gave TDB x9.8; now one line, exit 2."""
    from cli import main as cli

    p = _tsv(sweep_log, tmp_path / "ext.tsv")
    with pytest.raises(StationError) as err:
        import_log(p, time_units="ms")
    med = np.median(np.linalg.norm(sweep_log.acc_g * G0_M_S2, axis=1))
    assert str(err.value) == (f"{p}: acc_x/acc_y/acc_z look like m/s2, not g (median |a| = {med:.3g}): "
                              "give --accel-units m/s2")
    rc = cli.main(["diagnose", str(p), "--time-units", "ms"])
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and lines == [f"station diagnose: error: {err.value}"]
    # mg and kelvin, converted by the options the errors name
    text = "# serial: MG1\nt;x;y;z;temp_c\n" + "".join(f"{k * 0.5};1;-2;1000.5;{298.15 + k * 0.01:.2f}\n" for k in range(20))
    with pytest.raises(StationError, match=r"^<log>: x/y/z look like mg, not g \(median \|a\| = 1001\): give --accel-units mg$"):
        parse_import(text)
    with pytest.raises(StationError, match=r"^<log>: temp_c looks like kelvin, not C \(median 298.25\): give --temp-units K$"):
        parse_import(text, accel_units="mg")
    log = parse_import(text, accel_units="mg", temp_units="K")
    assert log.acc_g[0].tolist() == pytest.approx([1e-3, -2e-3, 1.0005])
    assert log.temp_c[0] == pytest.approx(25.0)


def test_imucal_real_counts_are_recognised(tmp_path):
    """Real third-party data (../shared/data/imucal, raw counts of a +-16 g part, ~2048 LSB per g)."""
    from test_imucal_real_data import DATA_DIR, PARTS, load_session

    if not (DATA_DIR / "annotated_session.csv").exists():
        pytest.skip("imucal data not present")
    acc = np.concatenate([load_session().samples[p] for p in PARTS])
    rows = "".join(f"{k / 102.4:.6f};{a[0]:.0f};{a[1]:.0f};{a[2]:.0f};24.5\n" for k, a in enumerate(acc))
    p = tmp_path / "imucal.csv"
    p.write_text("time;acc_x;acc_y;acc_z;temp\n" + rows)
    med = float(np.median(np.linalg.norm(acc, axis=1)))
    assert 2000 < med < 2100
    with pytest.raises(StationError) as err:
        import_log(p)
    assert str(err.value) == (f"{p}: acc_x/acc_y/acc_z look like raw counts, not g (median |a| = {med:.0f}): give "
                              f"--accel-units counts --counts-per-g N (N = the sensor's LSB per g, about {med:.0f} here)")
    log = import_log(p, accel_units="counts", counts_per_g=2048.0)
    assert np.median(np.linalg.norm(log.acc_g, axis=1)) == pytest.approx(med / 2048.0)


@pytest.mark.parametrize("rows,needle", [
    ("0;0;0;1;25\n2;0;0;1;25\n1;0;0;1;25\n", "line 5: t = 1.0 goes back from 2.0 on line 4 (rows out of order?)"),
    ("5;0;0;1;25\n5;0;0;1;25\n5;0;0;1;25\n", "t is 5.0 in every row"),
    ("0;0;0;1;25\n1;0;0;1;25\n1;0;0;1;25\n", "line 5: t = 1.0 repeats line 4 (a duplicated row?)"),
    ("0;0;0;1;25\n1;0;0;1;25\n2;0;0;1;999\n", "line 5: temp = 999.0 is outside -60..150 C"),
])
def test_time_and_temperature_of_an_import_name_the_line(rows, needle):
    with pytest.raises(StationError) as err:
        parse_import("# serial: X\nt;x;y;z;temp\n" + rows, "f.csv")
    assert str(err.value).startswith("f.csv: ") and needle in str(err.value)


@pytest.mark.parametrize("value,why", [("1e9", "out of range"), ("0", "out of range"), ("nan", "not a finite number"),
                                       ("inf", "not a finite number"), ("-5", "out of range"), ("fast", "not a number")])
def test_an_imports_header_numbers_are_checked(value, why):
    with pytest.raises(StationError) as err:
        parse_import(f"# odr_hz: {value}\nt;x;y;z;temp\n0;0;0;1;25\n1;0;0;1;25\n", "f.csv")
    assert str(err.value) == f"f.csv: header '# odr_hz: {value}' is {why} (0 < odr_hz <= 100000 Hz)"


def test_incomplete_rows_are_skipped_across_chunks(monkeypatch):
    """Another sensor's lines in a shared log (other field count, empty fields) are skipped, in
    whichever block of the file they fall."""
    import contracts.logfile as lf

    good = [f"{k * 0.01:.2f},0,0,1,25" for k in range(400)]
    lines = list(good)
    lines.insert(150, "1.505,gyro,,")
    lines.insert(300, "2.995,,,,")
    text = "time,ax,ay,az,temp\n" + "\n".join(lines) + "\n"
    whole = parse_import(text)
    monkeypatch.setattr(lf, "CHUNK_BYTES", 100)
    small = parse_import(text)
    assert len(whole) == len(small) == 400
    np.testing.assert_array_equal(whole.time_s, small.time_s)
    np.testing.assert_array_equal(whole.time_s, np.array([float(f"{k * 0.01:.2f}") for k in range(400)]))
