"""The `station` command: user mistakes give one line on stderr and a non-zero exit, no traceback."""

import subprocess
import sys


def _station(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True, timeout=120)


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


def test_unknown_profile_is_one_line_and_non_zero_before_any_hardware():
    """demo --once and serve --start-batch with a profile that does not exist (issue 9)."""
    from pathlib import Path

    example = Path(__file__).resolve().parents[1] / "station.example.toml"
    for args in (("demo", "--once", "--profile", "nope"), ("serve", "--config", str(example), "--start-batch", "nope")):
        out = _station(*args)
        assert out.returncode != 0, args
        assert "Traceback" not in out.stderr, (args, out.stderr)
        lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "unknown profile 'nope'" in lines[0] and "fast-thermal" in lines[0], (args, out.stderr)


def test_a_validation_batch_says_it_yields_no_calibration_result():
    out = _station("demo", "--once", "--profile", "validation", "--no-web", "--speed", "1000", "--serial", "1",
                   "--can", "0", "--db", "memory://")
    assert out.returncode == 0, out.stderr
    assert "finished" in out.stdout and "no calibration result" in out.stdout, out.stdout


def test_an_error_with_control_characters_stays_one_line(monkeypatch, capsys):
    """Seen in CI: a corrupted SQLite file's error text carried a \\x1c byte, and str.splitlines()
    (like a terminal or a log reader) broke the one-line error in two."""
    from cli import main as cli
    from contracts.types import StationError

    class _Boom:
        @staticmethod
        def run(args):
            raise StationError('database x is corrupted (unrecognized token: "\x1c\x1d"): restore it\nfrom a backup')

    parser = cli.build_parser()
    args = parser.parse_args(["calibrate", "x.csv"])
    monkeypatch.setattr(cli, "build_parser", lambda: _Parser(parser, args, _Boom))
    assert cli.main(["calibrate", "x.csv"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "\\x1c\\x1d" in err and "restore it\\nfrom" in err, err


class _Parser:
    def __init__(self, parser, args, module):
        self.parser, self.args, self.module = parser, args, module

    def parse_args(self, argv):
        self.args._module = self.module
        return self.args


def test_log_commands_share_the_import_and_units_options():
    """Issue 22: an error names the option that converts a log's units; calibrate, sfem and diagnose
    all have it (cli/commands/log_import.py add_import_arguments)."""
    for cmd in ("calibrate", "sfem", "diagnose"):
        out = _station(cmd, "--help")
        assert out.returncode == 0, cmd
        for opt in ("--accel-units", "--counts-per-g", "--temp-units", "--time-units", "--columns", "--delimiter"):
            assert opt in out.stdout, (cmd, opt)
        assert "m/s2" in out.stdout and "mg" in out.stdout, cmd


def test_a_log_in_m_s2_is_one_line_for_every_log_command(tmp_path):
    p = tmp_path / "ms2.csv"
    p.write_text("# serial: X\ntime_s,ax_g,ay_g,az_g,temp_c\n" + "".join(f"{k},0,0,9.81,25\n" for k in range(50)))
    for cmd in ("calibrate", "sfem", "diagnose"):
        out = _station(cmd, str(p), *(["--norm-only"] if cmd == "sfem" else []))
        assert out.returncode == 2 and "Traceback" not in out.stderr, (cmd, out.stderr)
        assert out.stderr.splitlines() == [f"station {cmd}: error: {p}: ax_g/ay_g/az_g look like m/s2, not g "
                                           "(median |a| = 9.81): give --accel-units m/s2"], cmd
