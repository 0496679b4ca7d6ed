"""File names built from data (issue 22): a serial from a log header never chooses where a file goes.

Seen on main: a log whose `# serial:` was `../../../../escape`, run through
`station diagnose ... --save-model models`, wrote `escape.model.json` four folders above `models/`;
`--plots` built `<serial>_<plot>.png` the same way. contracts/filenames.py is the one helper.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from contracts.filenames import _WINDOWS_DEVICES, HASH_LEN, MAX_LEN, check_inside, safe_name, safe_path
from contracts.types import StationError
from station.diagnostics.plots import DUT_PLOTS, REPORT_PLOTS

ROOT = Path(__file__).resolve().parents[1]
SAFE = re.compile(r"[A-Za-z0-9._+\-]+")


# ---- the helper ---------------------------------------------------------------------------------
def _assert_safe(name: str, max_len: int = MAX_LEN) -> None:
    assert name and len(name) <= max_len
    assert SAFE.fullmatch(name), name
    assert ".." not in name and not name.startswith((".", "-")) and not name.endswith(".")
    assert "/" not in name and "\\" not in name and "\x00" not in name


@given(st.text(max_size=300))
@settings(max_examples=600, deadline=None)
def test_any_value_becomes_a_safe_base_name(value):
    _assert_safe(safe_name(value))


@given(st.text(max_size=120), st.text(max_size=120))
@settings(max_examples=600, deadline=None)
def test_distinct_values_never_share_a_name(a, b):
    if a != b:
        assert safe_name(a) != safe_name(b)


@given(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_+\-]{0,30}", fullmatch=True))
@settings(max_examples=300, deadline=None)
def test_a_clean_serial_is_kept_as_it_is(value):
    if not re.search(r"-[0-9a-f]{%d}$" % HASH_LEN, value) and value.upper() not in _WINDOWS_DEVICES:
        assert safe_name(value) == value


@pytest.mark.parametrize("value", [
    "../../../../escape", "/tmp/x", "..", ".", "", "a/b", "a\\b", "a\x00b", "a\nb", "a\rb", "\u2028",
    "-rf", ".hidden", "x" * 5000, "C:\\Windows\\x", "NUL", "con.txt", "SIM0001/../..", "..\\..\\x", " ",
])
def test_hostile_values(value):
    name = safe_name(value)
    _assert_safe(name)
    assert name != value
    assert re.search(r"-[0-9a-f]{%d}$" % HASH_LEN, name)  # changed: the value's hash says so


def test_clean_examples_and_suffix_collisions():
    assert safe_name("SIM0001") == "SIM0001"
    assert safe_name("EXT-42_b.v2") == "EXT-42_b.v2"
    # a clean value that looks like a sanitised one is hashed too: no collision with "a/b"
    forged = safe_name("a/b")
    assert safe_name(forged) != forged
    assert len({safe_name(v) for v in ("a/b", "a\\b", "a:b", "a b", "a_b", forged)}) == 6


@given(st.text(max_size=200))
@settings(max_examples=300, deadline=None)
def test_safe_path_stays_directly_inside(tmp_path_factory, value):
    d = tmp_path_factory.getbasetemp() / "safe_path_prop"
    d.mkdir(exist_ok=True)
    p = safe_path(d, value, ".model.json")
    assert p.parent == d and p.resolve().parent == d.resolve()
    assert p.name.endswith(".model.json")


def test_safe_path_refuses_a_planted_symlink_and_bad_suffixes(tmp_path):
    d = tmp_path / "out"
    d.mkdir()
    (d / "SIM0001.csv").symlink_to(tmp_path / "elsewhere.csv")
    with pytest.raises(StationError, match="outside"):
        safe_path(d, "SIM0001", ".csv")
    with pytest.raises(ValueError):
        safe_path(d, "x", "/../y")
    with pytest.raises(StationError, match="outside"):
        check_inside(d, d / ".." / "x")
    assert check_inside(d, d / "x.png") == d / "x.png"


# ---- the commands: a hostile serial writes only inside the folder the user named ----------------
# a log's header line cannot hold a line break (str.splitlines splits there), so the control
# characters here are those that stay inside a line; a newline is tested in-process below
HOSTILE = ("../../../../escape", "..", "a\x00b\x1b[31mc\td\x7f/e")


def _tree(root: Path) -> set[str]:
    out = set()
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames + filenames:
            out.add(os.path.relpath(os.path.join(dirpath, n), root))
    return out


def _station(*args, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    out = _station("simulate", "--out", d, "--duts", "1", "--profile", "fast-thermal", "--seed", "2", "--quiet", cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return (d / "SIM0001.csv").read_text(encoding="utf-8")


def test_diagnose_save_model_and_plots_write_only_inside_the_named_folders(sim_log, tmp_path):
    # deep enough that ../../../../ stays inside tmp_path, so the walk below would see an escape
    work = tmp_path / "a" / "b" / "c" / "d" / "work"
    work.mkdir(parents=True)
    abs_target = tmp_path / f"abs-{uuid.uuid4().hex[:8]}"
    abs_tmp = Path("/tmp") / f"x-{uuid.uuid4().hex[:8]}"
    serials = (*HOSTILE, str(abs_target), str(abs_tmp))
    logs = []
    for k, serial in enumerate(serials):
        p = work / f"log{k}.csv"
        p.write_text(sim_log.replace("# serial: SIM0001", f"# serial: {serial}", 1), encoding="utf-8")
        logs.append(p.name)
    (work / "models").mkdir()
    before = _tree(tmp_path)
    out = _station("diagnose", *logs, "--candidates", "bias_t2", "--save-model", "models", "--plots", "plots", cwd=work)
    assert out.returncode == 0, out.stderr
    new = _tree(tmp_path) - before
    inside = {os.path.relpath(work / "models", tmp_path), os.path.relpath(work / "plots", tmp_path)}
    outside = [n for n in new if not any(n == d or n.startswith(d + os.sep) for d in inside)]
    assert outside == [], outside
    models = sorted((work / "models").iterdir())
    plots = sorted((work / "plots").iterdir())
    assert len(models) == len(serials)  # one per DUT: no two serials collide into one file
    assert len(plots) == len(DUT_PLOTS) * len(serials) + len(REPORT_PLOTS)
    for p in models + plots:
        assert p.parent.resolve() in ((work / "models").resolve(), (work / "plots").resolve())
        _assert_safe(p.name, MAX_LEN + len("_residual_vs_acceleration.png"))
    assert not abs_target.with_name(abs_target.name + ".model.json").exists()
    assert not list(Path("/tmp").glob(abs_tmp.name + "*"))


def test_diagnose_save_model_of_one_hostile_log_into_a_folder(sim_log, tmp_path):
    """The reported case: one log, `--save-model models` with models/ an existing folder."""
    work = tmp_path / "a" / "b" / "c" / "d" / "work"
    (work / "models").mkdir(parents=True)
    (work / "log.csv").write_text(sim_log.replace("# serial: SIM0001", "# serial: ../../../../escape", 1))
    before = _tree(tmp_path)
    out = _station("diagnose", "log.csv", "--candidates", "bias_t2", "--save-model", "models", cwd=work)
    assert out.returncode == 0, out.stderr
    new = _tree(tmp_path) - before
    assert len(new) == 1 and next(iter(new)).startswith(os.path.join("a", "b", "c", "d", "work", "models") + os.sep), new
    assert not list(tmp_path.rglob("escape.model.json"))


def test_a_serial_with_a_newline_or_nul_from_memory_stays_inside(tmp_path):
    """A DutLog built in memory (another tool, the database) can carry any character."""
    import diag_helpers as H
    from cli.commands.diagnose import _save_models
    from station.diagnostics.plots import write_plots
    from station.diagnostics.ranking import diagnose

    logs, _ = H.sim_logs((), profile=H.SWEEP[:2], seed=5, odr_hz=1.0)
    logs[0].meta["serial"] = "../x\n/../\x00y"
    report = diagnose(logs, candidates=["bias_t2"])
    d = tmp_path / "deep" / "out"
    before = _tree(tmp_path)
    files = write_plots(report, d) + _save_models(report, d / "models")
    new = _tree(tmp_path) - before
    assert all(n == "deep" or n.startswith(os.path.join("deep", "out")) for n in new), new
    assert all(p.resolve().parent in (d.resolve(), (d / "models").resolve()) for p in files)
    assert len(files) == len(DUT_PLOTS) + len(REPORT_PLOTS) + 1
