"""The command line touches nothing it was not asked to (issue 34, the CLI bullet).

- A command that reads a database (certificate, export, db check|export|prune, replay's source)
  opens an existing one only: without a database it says that none was given and where it looked,
  with a missing one it names the file; exit 2, one line on stderr, and the working directory is
  unchanged afterwards (no ./var/station.db, no ./var/). Only `station db upgrade` (and serve/demo,
  which own theirs) create a database.
- A reader that closes the pipe early (`station calibrate LOG --json | head -c 100`) ends the
  command quietly: exit 141 (128 + SIGPIPE) or 0 when everything was written in time, nothing on
  stderr (no traceback, no "Exception ignored").
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SIGPIPE_EXIT = 141

# every command that reads a database, with what it needs besides the database
READERS = {
    "certificate": ["certificate", "SIM0001", "--out", "cert.pdf"],
    "export stdf": ["export", "stdf", "--batch", "1", "--out", "out.stdf"],
    "export ocptv": ["export", "ocptv", "--run", "1", "--out", "out.json"],
    "db check": ["db", "check"],
    "db export": ["db", "export", "1", "--out", "run.csv"],
    "db prune": ["db", "prune", "--older-than", "30", "--export", "archive"],
    "replay": ["replay", "--batch", "1"],
}
# the option that names the database: `station db` takes it before its action
DB_FLAG = {name: "--url" if name.startswith("db ") else "--db" for name in READERS}


def _env(**extra: str) -> dict[str, str]:
    """The environment of a plain shell: no $STATION_DB_URL, and stdout block-buffered into a pipe
    as usual (no $PYTHONUNBUFFERED: buffered output is what fails again at exit, "Exception
    ignored ... BrokenPipeError")."""
    env = {k: v for k, v in os.environ.items() if k not in ("STATION_DB_URL", "PYTHONUNBUFFERED")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    return env


def _station(args: list[str], cwd: Path, env: dict[str, str] | None = None, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *args], cwd=cwd, env=env or _env(),
                          capture_output=True, text=True, timeout=120, **kw)


def _cli(args: list[str], cwd: Path, monkeypatch, capsys) -> tuple[int, str]:
    """`station ARGS` in this process (the same main() as the entry point, a second faster than a
    subprocess): its exit code and its one stderr line."""
    from cli.main import main

    monkeypatch.chdir(cwd)
    capsys.readouterr()
    rc = main(args)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return rc, lines[0]


def _with_db(name: str, value: str) -> list[str]:
    args = list(READERS[name])
    if name.startswith("db "):
        return ["db", "--url", value, *args[1:]]
    return [*args, "--db", value]


def _tree(folder: Path) -> dict[str, str]:
    """Every file and folder under `folder` with a digest of its bytes: 'nothing changed' is exact."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _one_line(r: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


@pytest.fixture()
def workdir(tmp_path: Path) -> Path:
    """A working directory with something in it (a log), so 'unchanged' is not 'still empty'."""
    folder = tmp_path / "work"
    folder.mkdir()
    (folder / "notes.txt").write_text("the operator's notes\n")
    return folder


def test_certificate_and_export_without_a_database_create_nothing(workdir):
    """The issue's two commands through the real entry point (a subprocess, a fresh directory)."""
    before = _tree(workdir)
    for args in (READERS["certificate"], READERS["export stdf"]):
        r = _station(args, workdir)
        line = _one_line(r)
        assert r.returncode == 2 and "no database given" in line and "station db upgrade" not in line, r.stderr
        assert str(workdir / "var" / "station.db") in line, line
    assert _tree(workdir) == before


@pytest.mark.parametrize("name", list(READERS))
def test_a_reading_command_without_a_database_names_where_it_looked_and_creates_nothing(
        name, workdir, monkeypatch, capsys):
    monkeypatch.delenv("STATION_DB_URL", raising=False)
    before = _tree(workdir)
    rc, line = _cli(READERS[name], workdir, monkeypatch, capsys)
    assert rc == 2, (name, line)
    assert line.startswith(f"station {name.split()[0]}: error: no database given"), line
    if name == "replay":  # a replay has no default database: it says so
        assert "a replay has no default database" in line and "--db" in line, line
    else:  # the option it lacked, the environment it consulted and the default path it tried
        assert f"no {DB_FLAG[name]}" in line and "$STATION_DB_URL is not set" in line, line
        assert f"none at the default var/station.db ({workdir / 'var' / 'station.db'})" in line, line
        assert "never creates one" in line, line
    assert _tree(workdir) == before, name


@pytest.mark.parametrize("name", list(READERS))
def test_a_missing_database_is_one_line_and_is_not_created(name, workdir, monkeypatch, capsys):
    monkeypatch.delenv("STATION_DB_URL", raising=False)
    before = _tree(workdir)
    for value in ("missing/station.db", f"sqlite:///{workdir / 'gone.db'}"):
        rc, line = _cli(_with_db(name, value), workdir, monkeypatch, capsys)
        assert rc == 2, (name, value, line)
        path = workdir / "missing" / "station.db" if value.startswith("missing") else workdir / "gone.db"
        assert f"database {path} ({DB_FLAG[name]} {value}): no such file" in line, line
        assert _tree(workdir) == before, (name, value)


def test_the_environment_and_the_config_are_named_when_their_database_is_missing(workdir, monkeypatch, capsys):
    cfg = workdir / "station.toml"
    cfg.write_text('database_url = "sqlite:///var/line-7.db"\n')
    no_url = workdir / "bare.toml"
    no_url.write_text('name = "line-7"\n')
    before = _tree(workdir)
    monkeypatch.setenv("STATION_DB_URL", "sqlite:///elsewhere/st.db")
    rc, line = _cli(READERS["certificate"], workdir, monkeypatch, capsys)
    assert rc == 2 and f"database {workdir / 'elsewhere' / 'st.db'} (from $STATION_DB_URL): no such file" in line
    monkeypatch.delenv("STATION_DB_URL")
    for name in ("export stdf", "db check"):
        for config in (cfg, no_url):
            args = ["db", "--config", str(config), "check"] if name == "db check" else \
                READERS[name] + ["--config", str(config)]
            rc, line = _cli(args, workdir, monkeypatch, capsys)
            assert rc == 2, line
            if config == cfg:
                assert f"database {workdir / 'var' / 'line-7.db'} (database_url in {cfg}): no such file" in line
            else:
                assert f"{no_url} has no database_url" in line and "none at the default" in line, line
    assert _tree(workdir) == before


def test_only_db_upgrade_creates_and_a_reader_leaves_the_database_file_as_it_was(workdir, monkeypatch, capsys):
    from cli.main import main

    monkeypatch.delenv("STATION_DB_URL", raising=False)
    monkeypatch.chdir(workdir)
    assert main(["db", "upgrade"]) == 0  # the one command whose job it is: at the default path
    assert "sqlite:///var/station.db at schema revision" in capsys.readouterr().out
    path = workdir / "var" / "station.db"
    assert path.is_file()
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert main(["db", "check"]) == 0  # the default now exists: it is used
    assert "(current)" in capsys.readouterr().out
    rc, line = _cli(READERS["certificate"], workdir, monkeypatch, capsys)
    assert rc == 2 and "no DUT with serial 'SIM0001' in sqlite:///var/station.db" in line, line
    rc, line = _cli(_with_db("export stdf", str(path)), workdir, monkeypatch, capsys)
    assert rc == 2 and "no batch 1" in line, line
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest  # opened read-only
    empty = workdir / "empty.db"
    empty.write_bytes(b"")
    rc, line = _cli(_with_db("certificate", str(empty)), workdir, monkeypatch, capsys)
    assert rc == 2 and "holds no station data (no schema" in line, line
    assert empty.read_bytes() == b""
    (workdir / "a-folder.db").mkdir()
    rc, line = _cli(_with_db("db check", str(workdir / "a-folder.db")), workdir, monkeypatch, capsys)
    assert rc == 2 and "is a directory, not a database file" in line, line


# ---- a closed pipe ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("logs")
    r = subprocess.run([sys.executable, "-m", "cli", "simulate", "--out", str(folder), "--duts", "1",
                        "--seed", "3"], capture_output=True, text=True, timeout=120, env=_env(), cwd=ROOT)
    assert r.returncode == 0, r.stderr
    (path,) = folder.glob("*.csv")
    return path


def _run_into_pipe(args: list[str], read: int, pipe_size: int | None = None, stream: str = "stdout",
                   env: dict[str, str] | None = None):
    """Run `station ARGS` with `stream` into a real pipe of which the reader takes `read` bytes
    (0: closed before the command starts) and then closes its end, as `| head -c N` does."""
    r_fd, w_fd = os.pipe()
    if pipe_size:
        fcntl.fcntl(w_fd, fcntl.F_SETPIPE_SZ, pipe_size)
    if read == 0:
        os.close(r_fd)
    kw = {"stdout": w_fd, "stderr": subprocess.PIPE} if stream == "stdout" else \
        {"stdout": subprocess.DEVNULL, "stderr": w_fd}
    p = subprocess.Popen([sys.executable, "-m", "cli", *args], env=env or _env(), cwd=ROOT, **kw)
    os.close(w_fd)
    got = b""
    if read:
        with os.fdopen(r_fd, "rb", buffering=0) as reader:
            while len(got) < read:
                chunk = reader.read(read - len(got))
                if not chunk:
                    break
                got += chunk
    err = p.stderr.read().decode() if p.stderr else ""
    return p.wait(timeout=120), got, err


@pytest.mark.parametrize("unbuffered", [False, True], ids=["buffered", "PYTHONUNBUFFERED"])
def test_calibrate_json_into_head_ends_quietly(log, unbuffered):
    env = _env(**({"PYTHONUNBUFFERED": "1"} if unbuffered else {}))
    # the pipe holds one page: the reader takes 100 bytes and leaves while the command still writes
    # the rest of its ~9 kB of JSON, exactly `station calibrate LOG --json | head -c 100`
    rc, got, err = _run_into_pipe(["calibrate", str(log), "--json"], read=100, pipe_size=4096, env=env)
    assert len(got) == 100 and got.startswith(b"{"), got
    assert err == "" and rc == SIGPIPE_EXIT, (rc, err)
    # a reader gone before the first byte (`| true`)
    rc, _, err = _run_into_pipe(["calibrate", str(log), "--json"], read=0, env=env)
    assert err == "" and rc == SIGPIPE_EXIT, (rc, err)
    # the table too, and any other command: it is handled once, in cli/main.py
    rc, _, err = _run_into_pipe(["calibrate", str(log)], read=0, env=env)
    assert err == "" and rc == SIGPIPE_EXIT, (rc, err)


def test_a_real_shell_pipeline_into_head(log):
    r = subprocess.run(["bash", "-c", f'"{sys.executable}" -m cli calibrate "{log}" --json | head -c 100; '
                        'echo " status=${PIPESTATUS[0]}"'], capture_output=True, text=True, timeout=120,
                       env=_env(), cwd=ROOT)
    body, _, status = r.stdout.rpartition(" status=")
    assert len(body) == 100 and r.stderr == "", r.stderr
    assert int(status) in (0, SIGPIPE_EXIT)  # 0 when the JSON fitted in the pipe before head left


def test_help_and_an_error_into_a_closed_pipe_end_quietly(tmp_path):
    # argparse prints into stdout's buffer and exits; main flushes it before the exit. (Unbuffered,
    # argparse itself drops the write error and exits 0: quiet as well.)
    rc, _, err = _run_into_pipe(["--help"], read=0)
    assert err == "" and rc == SIGPIPE_EXIT, (rc, err)
    rc, _, _ = _run_into_pipe(["calibrate", str(tmp_path / "missing.csv")], read=0, stream="stderr")
    assert rc == SIGPIPE_EXIT  # `2>&1 | true`: the one-line error has nowhere to go, no second error either


def test_a_broken_pipe_of_the_station_own_links_is_not_swallowed(monkeypatch):
    """Only a closed stdout/stderr ends quietly: a BrokenPipeError from a socket or pty of the
    station's links is a real error and still raises."""
    from cli import main as cli

    class _Link:
        @staticmethod
        def run(args):
            raise BrokenPipeError(32, "Broken pipe (a Modbus socket)")

    parser = cli.build_parser()
    args = parser.parse_args(["calibrate", "x.csv"])
    args._module = _Link
    monkeypatch.setattr(parser, "parse_args", lambda argv: args)
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    with pytest.raises(BrokenPipeError):
        cli.main(["calibrate", "x.csv"])
