"""The `station` command: user mistakes give one line on stderr and a non-zero exit, no traceback."""

import subprocess
import sys


def _station(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "station.cli", *args], capture_output=True, text=True, timeout=120)


def test_help_lists_every_command():
    out = _station("--help")
    assert out.returncode == 0
    for name in ("demo", "serve", "simulate", "calibrate", "sfem", "diagnose"):
        assert name in out.stdout


def test_missing_log_file_is_one_line_without_traceback(tmp_path):
    for cmd in ("calibrate", "sfem", "diagnose"):
        out = _station(cmd, str(tmp_path / "missing.csv"))
        assert out.returncode != 0, cmd
        assert "Traceback" not in out.stderr, cmd
        lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, (cmd, out.stderr)
        assert "missing.csv" in lines[0]
