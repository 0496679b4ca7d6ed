"""The ranking cache of `station diagnose` on disk (station/diagnostics/disk_cache.py, issue 38).

A first `station diagnose LOG.csv` ranks the candidates and keeps the ranking in the user's cache
folder ($STATION_DIAGNOSE_CACHE here: a folder of the test); the next run on the same log, with
the same candidates, effects and software, reuses it (`--add EFFECT` then fits only the added
models). What is checked: the report is the same as a cold run's, anything that changes the
question misses (one byte of the log, the effects file, the software version), a damaged or foreign
cache file is ignored and replaced, a folder that cannot be written just means no cache, and a
library call (no command line) writes nothing.

Most runs call the command line in-process (cli.main.main) with the ranking counted (ranking._rank
wrapped) and the process's own memory of rankings (ranking._RANKED) emptied before each run, so
only the disk can answer; one test runs the command as a separate process, as a user does.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

import diag_helpers as H
from cli.main import main
from contracts.logfile import format_log
from station.diagnostics import disk_cache, ranking
from station.diagnostics.effects import REGISTRY

ROOT = Path(__file__).resolve().parents[1]
CANDIDATES = ("--candidates", "bias_t2,bias_t3")  # two linear candidates: a ranking in a fraction of a second
POSIX_USER = hasattr(os, "getuid") and os.getuid() != 0  # root writes into a read-only folder anyway

EFFECTS_FILE = '''"""A user's effect for the cache tests: the bias drift bends at a knee."""
import numpy as np

from station.diagnostics.effects import Effect, register

KNEE_C = 10.0


class CacheKnee(Effect):
    name = "cache_knee"
    linear = ("k_mg_per_c",)
    block_level = True

    def columns(self, ctx, nl):
        return np.repeat(np.maximum(ctx.dt_c - KNEE_C, 0.0)[:, None, None], 3, axis=1)


register(CacheKnee())
'''


@pytest.fixture(scope="module")
def log_text() -> str:
    """A short simulated log (a chamber triangle at 1 C/min in two orientations, 1 Hz) with a bias curvature."""
    logs, _ = H.sim_logs(("bias_t2",), profile=H.SINGLE_RATE, seed=5, odr_hz=1.0)
    return format_log(logs[0])


@pytest.fixture
def work(tmp_path, monkeypatch, log_text):
    cache = tmp_path / "cache"
    monkeypatch.setenv(disk_cache.ENV, str(cache))
    log = tmp_path / "logs" / "SIM0001.csv"
    log.parent.mkdir()
    log.write_text(log_text, encoding="utf-8")
    ranked: list[int] = []  # one entry per ranking actually computed
    real_rank = ranking._rank

    def counting_rank(*args, **kw):
        ranked.append(1)
        return real_rank(*args, **kw)

    monkeypatch.setattr(ranking, "_rank", counting_rank)
    registry = dict(REGISTRY)  # --effects-file registers into the process's library: put it back after
    ranking._RANKED.clear()
    yield SimpleNamespace(log=log, cache=cache, ranked=ranked, tmp=tmp_path)
    REGISTRY.clear()
    REGISTRY.update(registry)
    ranking._RANKED.clear()


def _diagnose(capsys, *args) -> dict:
    """`station diagnose ARGS --json` in this process, with no ranking in memory: the JSON report."""
    ranking._RANKED.clear()
    rc = main(["diagnose", *map(str, args), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    return json.loads(out.out)


def _files(cache: Path) -> list[Path]:
    return sorted(cache.glob("*" + disk_cache.SUFFIX)) if cache.is_dir() else []


def test_a_warm_cache_gives_the_same_report_as_a_cold_run(work, capsys):
    cold = _diagnose(capsys, work.log, *CANDIDATES)
    assert len(work.ranked) == 1 and len(_files(work.cache)) == 1
    warm = _diagnose(capsys, work.log, *CANDIDATES)
    assert len(work.ranked) == 1, "the second run ranked again instead of reading the cache"
    assert warm == cold
    # --add on the cached ranking: the same report as without any cache
    added = _diagnose(capsys, work.log, *CANDIDATES, "--add", "bias_t3")
    assert len(work.ranked) == 1
    uncached = _diagnose(capsys, work.log, *CANDIDATES, "--add", "bias_t3", "--no-cache")
    assert len(work.ranked) == 2 and added == uncached
    assert [s["model"] for s in added["staircase"]] == ["baseline", "+bias_t3"]


def test_a_changed_log_byte_misses(work, capsys):
    first = _diagnose(capsys, work.log, *CANDIDATES)
    original = work.log.read_text(encoding="utf-8")
    lines = original.splitlines(keepends=True)
    k = next(i for i, ln in enumerate(lines) if ln[:1].isdigit())  # the first data row
    row = lines[k].rstrip("\n").split(",")
    row[3] = row[3][:-1] + ("1" if row[3][-1] != "1" else "2")  # az_g's last digit: 1e-7 g
    lines[k] = ",".join(row) + "\n"
    work.log.write_text("".join(lines), encoding="utf-8")
    second = _diagnose(capsys, work.log, *CANDIDATES)
    assert len(work.ranked) == 2 and len(_files(work.cache)) == 2
    assert second["ranking"] and second["serials"] == first["serials"]
    work.log.write_text(original, encoding="utf-8")  # and back: the first ranking is still there
    assert _diagnose(capsys, work.log, *CANDIDATES) == first and len(work.ranked) == 2


def test_a_changed_effects_file_misses_and_the_same_content_hits(work, capsys):
    effects = work.tmp / "my_effects.py"
    effects.write_text(EFFECTS_FILE, encoding="utf-8")
    args = (work.log, "--effects-file", effects, "--candidates", "cache_knee,bias_t2")
    first = _diagnose(capsys, *args)
    assert len(work.ranked) == 1 and any(r["effect"] == "cache_knee" for r in first["ranking"])
    effects.write_text(EFFECTS_FILE, encoding="utf-8")  # rewritten, same bytes: the same effect
    assert _diagnose(capsys, *args) == first and len(work.ranked) == 1
    effects.write_text(EFFECTS_FILE.replace("KNEE_C = 10.0", "KNEE_C = 12.0"), encoding="utf-8")
    changed = _diagnose(capsys, *args)
    assert len(work.ranked) == 2, "another effect definition reused the old ranking"
    assert changed["ranking"] != first["ranking"]


def test_another_software_version_misses(work, capsys, monkeypatch):
    import station.version

    first = _diagnose(capsys, work.log, *CANDIDATES)
    monkeypatch.setattr(station.version, "software_version", lambda: "0.0.0+another")
    again = _diagnose(capsys, work.log, *CANDIDATES)
    assert len(work.ranked) == 2 and len(_files(work.cache)) == 2
    assert again == first


def test_other_candidates_or_basis_miss(work, capsys):
    _diagnose(capsys, work.log, *CANDIDATES)
    _diagnose(capsys, work.log, "--candidates", "bias_t3,bias_t2")  # another order: another question
    _diagnose(capsys, work.log, *CANDIDATES, "--basis", "sample")
    assert len(work.ranked) == 3 and len(_files(work.cache)) == 3


@pytest.mark.parametrize("damage", ["flip a payload byte", "truncated", "not a cache file", "another question",
                                    "empty"])
def test_a_corrupt_cache_file_is_ignored_and_replaced(work, capsys, damage):
    cold = _diagnose(capsys, work.log, *CANDIDATES)
    (path,) = _files(work.cache)
    blob = path.read_bytes()
    if damage == "flip a payload byte":
        k = len(blob) - 100
        blob = blob[:k] + bytes([blob[k] ^ 0x01]) + blob[k + 1:]
    elif damage == "truncated":
        blob = blob[: len(blob) // 2]
    elif damage == "not a cache file":
        blob = b"import os; os.system('echo never run')\n" * 10
    elif damage == "another question":  # a valid file of another question put under this name
        head, _, payload = blob.partition(b"\n")[2].partition(b"\n")
        header = json.loads(head)
        header["key"]["basis"] = "sample"
        blob = disk_cache.MAGIC + json.dumps(header).encode() + b"\n" + payload
    else:
        blob = b""
    path.write_bytes(blob)
    again = _diagnose(capsys, work.log, *CANDIDATES)
    assert len(work.ranked) == 2, "a damaged cache file was believed"
    assert again == cold
    assert _files(work.cache) == [path] and path.read_bytes() != blob  # replaced by a good one
    assert _diagnose(capsys, work.log, *CANDIDATES) == cold and len(work.ranked) == 2  # which is read


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="file owners and modes are POSIX")
def test_a_cache_file_others_may_write_is_not_read(work, capsys):
    cold = _diagnose(capsys, work.log, *CANDIDATES)
    (path,) = _files(work.cache)
    path.chmod(0o666)
    assert _diagnose(capsys, work.log, *CANDIDATES) == cold and len(work.ranked) == 2
    assert path.stat().st_mode & 0o077 == 0  # replaced by the user's own file
    target = work.tmp / "elsewhere.diag"  # a symbolic link to a good file: not followed
    shutil.copy(path, target)
    path.unlink()
    path.symlink_to(target)
    assert _diagnose(capsys, work.log, *CANDIDATES) == cold and len(work.ranked) == 3


def test_a_cache_folder_that_cannot_be_written_means_no_cache(work, capsys, monkeypatch):
    cold = _diagnose(capsys, work.log, *CANDIDATES, "--no-cache")
    assert not work.cache.exists()
    blocker = work.tmp / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(disk_cache.ENV, str(blocker / "cache"))  # mkdir fails, whoever runs the test
    assert _diagnose(capsys, work.log, *CANDIDATES) == cold
    assert _diagnose(capsys, work.log, *CANDIDATES) == cold and len(work.ranked) == 3
    monkeypatch.setenv(disk_cache.ENV, "off")
    assert _diagnose(capsys, work.log, *CANDIDATES) == cold and len(work.ranked) == 4
    assert not any(p.suffix == disk_cache.SUFFIX for p in work.tmp.rglob("*"))


@pytest.mark.skipif(not POSIX_USER, reason="needs a user whom a read-only folder stops (not root)")
def test_read_only_folders_work_without_a_cache(work, capsys, monkeypatch):
    cold = _diagnose(capsys, work.log, *CANDIDATES, "--no-cache")
    ro = work.tmp / "ro-cache"
    ro.mkdir()
    ro.chmod(0o500)
    monkeypatch.setenv(disk_cache.ENV, str(ro))
    work.log.parent.chmod(0o555)  # the log's own folder read-only too
    try:
        assert _diagnose(capsys, work.log, *CANDIDATES) == cold
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o700)
        work.log.parent.chmod(0o755)


def test_a_library_call_writes_no_cache(work):
    ranking.diagnose([str(work.log)], candidates=["bias_t2"])
    assert not work.cache.exists()


def _station(*args, env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=ROOT, env=env)


def test_the_command_line_reuses_its_ranking_across_processes(work):
    """As a user runs it: a first `station diagnose`, then `--add` in a new process reads the
    ranking the first one wrote; the reports are those of runs without a cache. The ranking cache
    in a folder that cannot be created changes nothing either."""
    env = dict(os.environ, **{disk_cache.ENV: str(work.cache)})
    cold = _station("diagnose", work.log, *CANDIDATES, "--json", env=env)
    assert cold.returncode == 0, cold.stderr
    (path,) = _files(work.cache)
    written = path.stat()
    add = _station("diagnose", work.log, *CANDIDATES, "--add", "bias_t3", "--json", env=env)
    assert add.returncode == 0, add.stderr
    assert path.stat().st_ino == written.st_ino  # read (a miss would have replaced it)
    plain = _station("diagnose", work.log, *CANDIDATES, "--add", "bias_t3", "--json", "--no-cache", env=env)
    assert json.loads(add.stdout) == json.loads(plain.stdout)
    blocked = dict(env, **{disk_cache.ENV: str(path / "cache")})  # under a file: cannot be created
    nocache = _station("diagnose", work.log, *CANDIDATES, "--json", env=blocked)
    assert nocache.returncode == 0 and nocache.stderr == "", nocache.stderr
    assert json.loads(nocache.stdout) == json.loads(cold.stdout)
