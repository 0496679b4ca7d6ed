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
from station.log_import import G0_M_S2, import_log, parse_import
from station.logfile import write_log
from station.types import StationError

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
    a = subprocess.run([sys.executable, "-m", "station.cli", "diagnose", own, *args], capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    b = subprocess.run([sys.executable, "-m", "station.cli", "diagnose", ext, *args, "--accel-units", "m/s2",
                        "--time-units", "ms", "--columns", "time=timestamp,temp=temperature"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert a.returncode == 0, a.stderr
    assert b.returncode == 0, b.stderr
    da, db = json.loads(a.stdout), json.loads(b.stdout)
    assert db["serials"] == ["EXT42"]
    assert da["admitted"] == db["admitted"] == ["bias_t2"]
    assert db["baseline"]["heldout_rms_mg"] == pytest.approx(da["baseline"]["heldout_rms_mg"], rel=1e-3)
