"""Hostile log files (issue 37): each is one line on stderr and exit 2, or accepted when legitimate.

Measured on main before: one row with `ay_g = 1e308` was accepted (z TDSF -51.7 -> -60.5 ppm/C,
exit 0); a spreadsheet's "CSV UTF-8" (a BOM before the first line) was "missing column(s)"; 2 GB of
NUL bytes after a valid start took 12.7 GB and 93 s before its error. Now a sample beyond the
sensor's range (|a| > 16 g on an axis, a temperature outside -60..150 C) names its file line and
column like NaN does (contracts/log_checks.py), a BOM is skipped, and a file that is not text is
refused as soon as the block holding the NUL byte / undecodable byte / overlong line is read
(contracts/logfile.py), in bounded memory.

Every case runs the real command line in a subprocess (`python -m cli`, as test_cli.py),
on files written to tmp_path; `write_cases` and `run_measured` are also benchmarks/bad_files.py's.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from contracts.logfile import DutLog, check_log, format_log
from contracts.types import StationError
from thermal_synth import fast_thermal

ROOT = Path(__file__).resolve().parents[1]
META = {"serial": "SYN0001", "sensor": "LIS3DSH", "odr_hz": "3.125"}
FIRST_ROW_LINE = len(META) + 2  # the metadata lines, the header row, then the first data row
COL = {"time_s": 0, "ax_g": 1, "ay_g": 2, "az_g": 3, "temp_c": 4}
G0 = 9.80665


def good_log() -> DutLog:
    rec = fast_thermal(seed=8, tdb_mg_per_c=(0.47, 0.07, -0.2), tdsf_ppm_per_c=(-125.0, -38.0, -58.0))
    return DutLog(rec.time_s, rec.acc_g, rec.temp_c, meta=dict(META), position=rec.position.astype(np.int64))


def _set(text: str, row: int, column: str, value: str) -> tuple[str, int]:
    """The log text with data row `row` (0-based) holding `value` in `column`; and its file line."""
    lines = text.splitlines()
    k = FIRST_ROW_LINE - 1 + row
    fields = lines[k].split(",")
    fields[COL[column]] = value
    lines[k] = ",".join(fields)
    return "\n".join(lines) + "\n", k + 1


# name -> (file name, extra CLI options, expected exit code, the one stderr line after "<file>: " as
# a regex; None: accepted)
def write_cases(folder: Path, nul_bytes: int = 200 * 10**6) -> dict[str, tuple[Path, list[str], int, str | None]]:
    """Every bad file of the issue (and the good one), written to `folder`. The NUL file is sparse:
    a valid start, then `nul_bytes` of holes (truncate), costing no disk."""
    folder.mkdir(parents=True, exist_ok=True)
    log = good_log()
    text = format_log(log)
    lines = text.splitlines()
    cases: dict[str, tuple[Path, list[str], int, str | None]] = {}

    def put(name: str, body: str | bytes, expect: str | None, opts: list[str] | None = None, fname: str = "") -> None:
        p = folder / (fname or f"{name.split()[0]}.csv")
        p.write_bytes(body if isinstance(body, bytes) else body.encode())
        cases[name] = (p, opts or [], 2 if expect else 0, expect)

    put("good", text, None)
    bad, line = _set(text, 200, "ay_g", "1e308")
    put("ay_g=1e308", bad, rf"line {line}: ay_g = 1e\+308 is outside the sensor's range -16\.\.16 g", fname="huge.csv")
    bad, line = _set(text, 300, "az_g", "-17.5")
    put("az_g=-17.5", bad, rf"line {line}: az_g = -17\.5 is outside the sensor's range -16\.\.16 g", fname="g17.csv")
    bad, line = _set(text, 50, "temp_c", "1e308")
    put("temp_c=1e308", bad, rf"line {line}: temp_c = 1e\+308 is outside -60\.\.150 C", fname="hot.csv")
    bad, line = _set(text, 120, "ay_g", "nan")
    put("ay_g=nan", bad, rf"line {line}: ay_g = nan is not a finite number", fname="nan.csv")
    ms2 = DutLog(log.time_s, log.acc_g * G0, log.temp_c, meta=dict(META), position=log.position)
    put("m/s2", format_log(ms2),
        r"ax_g/ay_g/az_g look like m/s2, not g \(median \|a\| = 10\.1\): give --accel-units m/s2", fname="ms2.csv")
    kelvin = DutLog(log.time_s, log.acc_g, log.temp_c + 273.15, meta=dict(META), position=log.position)
    put("kelvin", format_log(kelvin), r"temp_c looks like kelvin, not C \(median 312\.\d\d\): give --temp-units K")
    rows = list(lines)
    k = FIRST_ROW_LINE - 1 + 400
    rows[k], rows[k + 1] = rows[k + 1], rows[k]
    put("time backwards", "\n".join(rows) + "\n",
        rf"line {k + 2}: time_s = [0-9.]+ goes back from [0-9.]+ on line {k + 1} \(rows out of order\?\): "
        "sample times must increase", fname="backwards.csv")
    put("BOM (CSV UTF-8)", b"\xef\xbb\xbf" + text.encode(), None, fname="bom.csv")
    start = "\n".join(lines[:500]) + "\n"
    put("overlong line", start + "1" * 300_000 + "\n" + "\n".join(lines[500:]) + "\n",
        r"line 501: longer than 65536 characters: not a text log \(a binary file or a damaged copy\?\)",
        fname="overlong.csv")
    put("not UTF-8", start.encode() + bytes(range(0x80, 0x100)) * 64,
        r"line 501: byte 0x80 is not UTF-8 text: save the log as UTF-8 \(CSV UTF-8\)", fname="binary.csv")
    put("NUL in a # line", text.replace("# sensor: LIS3DSH", "# note: a\x00b\n# sensor: LIS3DSH", 1), None,
        fname="nul_meta.csv")  # metadata's own business (test_safe_names: a hostile serial)
    put("# line + NULs", "# note: " + "\x00" * 300_000, r"line 1: longer than 65536 characters: not a text log "
        r"\(a binary file or a damaged copy\?\)", fname="nul_comment.csv")
    p = folder / "nul.csv"
    with open(p, "w") as f:  # a valid start, then holes: NUL bytes when read, no disk
        f.write(start)
        f.truncate(len(start.encode()) + nul_bytes)
    cases[f"NUL x {nul_bytes / 1e6:.0f} MB"] = (p, [], 2, r"line 501: NUL byte: not a text log \(a binary file or a "
                                                          r"damaged copy\?\)")
    return cases


# A small parent for the command: a child's ru_maxrss carries its parent's peak (vfork/exec), and
# pytest's is hundreds of MB; this one's is ~15 MB.
LAUNCHER = textwrap.dedent("""
    import json, resource, subprocess, sys, time
    t0 = time.monotonic()
    p = subprocess.run(sys.argv[2:], capture_output=True, text=True, cwd=sys.argv[1])
    s = time.monotonic() - t0
    mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(json.dumps({"rc": p.returncode, "out": p.stdout, "err": p.stderr, "peak_mb": mb, "s": s}))
""")


def run_measured(args: list[str], cwd: Path, timeout: float = 600) -> dict:
    """`python -m cli ARGS` in cwd: exit code, stdout, stderr, its peak RSS (MB), seconds."""
    out = subprocess.run([sys.executable, "-c", LAUNCHER, str(cwd), sys.executable, "-m", "cli", *args],
                         capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def _station(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    return write_cases(tmp_path_factory.mktemp("bad_files"))


@pytest.fixture(scope="module")
def good_out(cases):
    p = cases["good"][0]
    out = _station("calibrate", p.name, "--json", cwd=p.parent)
    assert out.returncode == 0 and out.stderr == "", out.stderr
    return out.stdout


def _one_line(out: subprocess.CompletedProcess | dict, cmd: str, p: Path, pattern: str) -> None:
    err = out["err"] if isinstance(out, dict) else out.stderr
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert re.fullmatch(rf"station {cmd}: error: {re.escape(p.name)}: {pattern}", lines[0]), lines[0]


BAD = ["ay_g=1e308", "az_g=-17.5", "temp_c=1e308", "ay_g=nan", "m/s2", "kelvin", "time backwards", "overlong line",
       "not UTF-8", "# line + NULs"]


@pytest.mark.parametrize("name", BAD)
def test_each_bad_file_is_one_line_and_exit_2_with_nothing_on_stdout(cases, name):
    p, opts, code, pattern = cases[name]
    out = _station("calibrate", p.name, "--json", *opts, cwd=p.parent)
    assert (out.returncode, out.stdout) == (code, "") == (2, "")
    _one_line(out, "calibrate", p, pattern)


def test_a_value_beyond_the_range_is_refused_by_every_log_command(cases):
    """sfem and diagnose read through the same reader and checks as calibrate."""
    p, _, _, pattern = cases["ay_g=1e308"]
    for cmd, extra in (("sfem", ["--norm-only"]), ("diagnose", [])):
        out = _station(cmd, p.name, *extra, cwd=p.parent)
        assert (out.returncode, out.stdout) == (2, ""), out.stderr
        _one_line(out, cmd, p, pattern)


def test_replay_of_a_bad_log_stores_nothing(cases, tmp_path):
    """station replay --logs reads with read_log: the same line, and no database is created."""
    db = tmp_path / "replay.db"
    for name in ("ay_g=1e308", f"NUL x {200:.0f} MB"):
        p, _, _, pattern = cases[name]
        out = _station("replay", "--logs", p.name, "--profile", "fast-thermal", "--db", f"sqlite:///{db}",
                       cwd=p.parent)
        assert out.returncode == 2, out.stderr
        _one_line(out, "replay", p, pattern)
        assert not db.exists() and not (p.parent / "var").exists()


@pytest.mark.parametrize("name", ["BOM (CSV UTF-8)", "NUL in a # line"])
def test_legitimate_files_are_accepted_and_give_the_good_files_result(cases, good_out, name):
    p = cases[name][0]
    out = _station("calibrate", p.name, "--json", cwd=p.parent)
    assert (out.returncode, out.stderr) == (0, "")
    got, want = json.loads(out.stdout), json.loads(good_out)
    got.pop("meta", None), want.pop("meta", None)  # the note line is metadata
    assert got == want


def test_an_import_in_other_units_is_checked_in_g(tmp_path):
    """Another tool's log in m/s2 (--accel-units m/s2): the range is 16 g in the file's units; a
    spreadsheet's BOM before its header is skipped too."""
    log = good_log()
    rows = ["timestamp\tacc_x\tacc_y\tacc_z\ttemperature"]
    rows += [f"{t * 1000:.3f}\t{a[0] * G0:.6f}\t{a[1] * G0:.6f}\t{a[2] * G0:.6f}\t{T:.3f}"
             for t, a, T in zip(log.time_s, log.acc_g, log.temp_c)]
    opts = ["--accel-units", "m/s2", "--time-units", "ms", "--json"]
    p = tmp_path / "ext.tsv"
    p.write_bytes(b"\xef\xbb\xbf" + ("\n".join(rows) + "\n").encode())
    ok = _station("calibrate", p.name, *opts, cwd=tmp_path)
    assert (ok.returncode, ok.stderr) == (0, ""), ok.stderr
    fields = rows[300].split("\t")
    fields[2] = "200.0"  # 20.4 g
    rows[300] = "\t".join(fields)
    p.write_text("\n".join(rows) + "\n")
    out = _station("calibrate", p.name, *opts, cwd=tmp_path)
    assert (out.returncode, out.stdout) == (2, "")
    _one_line(out, "calibrate", p, r"line 301: acc_y = 200\.0 is outside the sensor's range -16\.\.16 g "
                                   r"\(-156\.906\.\.156\.906 m/s2\)")


def test_the_rule_is_the_same_on_a_log_in_memory():
    """check_log (a DutLog from a stream or a database) applies the same rule, rows counted from 1;
    16 g itself is in range."""
    log = good_log()
    acc = log.acc_g.copy()
    acc[10, 2] = 16.0
    check_log(DutLog(log.time_s, acc, log.temp_c, meta=dict(META)), "mem")
    acc[20, 1] = 1e308
    with pytest.raises(StationError, match=r"^mem: row 21: ay_g = 1e\+308 is outside the sensor's range -16\.\.16 g$"):
        check_log(DutLog(log.time_s, acc, log.temp_c, meta=dict(META)), "mem")


def test_a_sparse_nul_file_fails_fast_in_bounded_memory(cases):
    """200 MB of NUL bytes after a valid start (2 GB before: 12.7 GB, 93 s)."""
    name = f"NUL x {200:.0f} MB"
    p, _, _, pattern = cases[name]
    r = run_measured(["calibrate", p.name], cwd=p.parent)
    assert (r["rc"], r["out"]) == (2, "")
    _one_line(r, "calibrate", p, pattern)
    assert r["peak_mb"] < 300, r["peak_mb"]
    assert r["s"] < 10, r["s"]
