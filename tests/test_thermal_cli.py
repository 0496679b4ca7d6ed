"""`station calibrate LOG.csv [--json]`: both methods, design 5.2 JSON shape, one-line user errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from cli import main as cli
from contracts.logfile import DutLog, write_log
from station.science.thermal_calibration import calibrate
from thermal_synth import fast_thermal

TRUTH = dict(tdb_mg_per_c=(0.47, 0.07, -0.2), tdsf_ppm_per_c=(-125.0, -38.0, -58.0))


def _log(path, rec, drop=None, meta=None, with_position=True):
    log = DutLog(rec.time_s, rec.acc_g, rec.temp_c, meta=meta or {"serial": "SYN0001", "sensor": "LIS3DSH"},
                 position=rec.position.astype(np.int64) if with_position else None)
    write_log(path, log)
    if drop:
        lines = path.read_text().splitlines()
        i = next(k for k, ln in enumerate(lines) if not ln.startswith("#"))
        cols = lines[i].split(",")
        j = cols.index(drop)
        path.write_text("\n".join(",".join(c for n, c in enumerate(ln.split(",")) if n != j) if k >= i else ln
                                  for k, ln in enumerate(lines)) + "\n")
    return path


@pytest.fixture(scope="module")
def good_log(tmp_path_factory):
    return _log(tmp_path_factory.mktemp("cal") / "dut.csv", fast_thermal(seed=8, **TRUTH))


def test_json_has_both_methods_and_the_offline_values_on_top(good_log, capsys):
    assert cli.main(["calibrate", str(good_log), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["serial"] == "SYN0001" and out["axes_method"] == "offline"
    for k, ax in enumerate("xyz"):
        top = out["axes"][ax]
        assert abs(top["tdb_mg_per_c"] - TRUTH["tdb_mg_per_c"][k]) < 0.03
        assert abs(top["tdsf_ppm_per_c"] - TRUTH["tdsf_ppm_per_c"][k]) < 40
        assert top == out["offline"]["axes"][ax] and top["tdb_sigma_mg_per_c"] > 0
        assert abs(out["streaming"]["axes"][ax]["tdb_mg_per_c"] - TRUTH["tdb_mg_per_c"][k]) < 0.03
        assert len(out["streaming"]["orientations"][ax]) == 2 and len(out["offline"]["orientations"][ax]) == 2
    assert out["streaming"]["method"] == "streaming" and out["offline"]["method"] == "offline"
    segs = out["segments"]
    assert [s["orientation"] for s in segs] == [0, 0, 1, 1]
    assert [s["position"] for s in segs] == [0, 0, 1, 1]  # from the log's position column
    assert all(s["n_samples"] == 1000 and len(s["acc_mean_g"]) == 3 for s in segs)


def test_human_table(good_log, capsys):
    assert cli.main(["calibrate", str(good_log)]) == 0
    text = capsys.readouterr().out
    assert "TDB mg/C" in text and "offline" in text and "streaming" in text and "SYN0001" in text
    assert "adopted: offline" in text


def test_calibrate_function_equals_cli(good_log, capsys):
    from contracts.logfile import read_log

    res = calibrate(read_log(good_log))
    assert cli.main(["calibrate", str(good_log), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(res))


def _err(argv, capsys):
    code = cli.main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    return lines[0]


def test_user_mistakes_are_one_line(tmp_path, capsys):
    assert "no such file" in _err(["calibrate", str(tmp_path / "nope.csv")], capsys)
    rec = fast_thermal(seed=1, **TRUTH)
    p = _log(tmp_path / "nocol.csv", rec, drop="temp_c")
    assert "temp_c" in _err(["calibrate", str(p)], capsys)
    # the lamp never heated: swing below the 20 C the method needs
    cold = fast_thermal(seed=1, lamp_rise_c=8.0, turned_extra_c=0.0, self_heating_c=1.0, **TRUTH)
    line = _err(["calibrate", str(_log(tmp_path / "cold.csv", cold))], capsys)
    assert "swing" in line and "20" in line
    # never turned over long enough: too few segments
    short = fast_thermal(seed=1, phases_min=(25.0, 30.0, 0.5, 0.5), **TRUTH)
    line = _err(["calibrate", str(_log(tmp_path / "short.csv", short))], capsys)
    assert "segment" in line and "orientation" in line
    # a header only
    (tmp_path / "empty.csv").write_text("time_s,ax_g,ay_g,az_g,temp_c\n")
    assert "samples" in _err(["calibrate", str(tmp_path / "empty.csv")], capsys)


def test_subprocess_exit_code_and_no_traceback(tmp_path):
    short = fast_thermal(seed=1, phases_min=(25.0, 30.0, 0.5, 0.5), **TRUTH)
    p = _log(tmp_path / "short.csv", short)
    out = subprocess.run([sys.executable, "-m", "cli", "calibrate", str(p), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr and out.stdout == ""
    assert len(out.stderr.strip().splitlines()) == 1
