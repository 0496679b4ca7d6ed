"""The house's seams are typed (docs/design.md section 2), and the type checker holds them.

- The daemon's parts and the verdict's decisions take no parameter typed `Any` and none
  unannotated: each names the narrow Protocol or the type it reads (counted with `ast`).
- No module of the product is over 500 lines (tests aside): one responsibility each.
- mypy --strict (pyproject.toml [tool.mypy], run by scripts/test.sh before any test) passes on the
  tree, and FAILS when a Station attribute the verdict's moment reads is renamed, or when the
  moment reads a context field by a name it does not have: the bug class that once judged every
  interrupted run as the wrong profile is a build error, not a wrong verdict at a restart.
"""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PRODUCT = ("cli", "contracts", "db", "drivers", "station", "web")
TYPED = ("station/daemon", "station/decisions")
MAX_LINES = 500


def _params(folder: str) -> tuple[list[str], list[str]]:
    """(parameters typed Any, parameters without annotation) of every function under `folder`."""
    typed_any, bare = [], []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
            for a in args:
                if a.arg in ("self", "cls"):
                    continue
                where = f"{path.relative_to(ROOT)}:{node.lineno} {node.name}({a.arg})"
                if a.annotation is None:
                    bare.append(where)
                elif re.search(r"\bAny\b", ast.unparse(a.annotation)):
                    typed_any.append(where)
    return typed_any, bare


@pytest.mark.parametrize("folder", TYPED)
def test_no_parameter_is_typed_any_or_left_bare(folder):
    typed_any, bare = _params(folder)
    assert not typed_any, f"parameters typed Any in {folder}: " + "; ".join(typed_any)
    assert not bare, f"parameters without a type in {folder}: " + "; ".join(bare)


def test_no_module_is_over_500_lines():
    long = []
    for pkg in PRODUCT:
        for path in sorted((ROOT / pkg).rglob("*.py")) if (ROOT / pkg).is_dir() else []:
            n = len(path.read_text().splitlines())
            if n > MAX_LINES:
                long.append(f"{path.relative_to(ROOT)} ({n} lines)")
    assert not long, "modules over 500 lines: " + ", ".join(long)


def _mypy(where: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary", "--cache-dir", str(where / ".mypy")],
                          cwd=where, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def tree_copy(tmp_path_factory):
    """The product's sources and its mypy config in a folder of their own (the tree is never edited)."""
    pytest.importorskip("mypy")
    where = tmp_path_factory.mktemp("typed")
    for pkg in PRODUCT:
        if (ROOT / pkg).is_dir():
            shutil.copytree(ROOT / pkg, where / pkg, ignore=shutil.ignore_patterns("__pycache__", "static"))
    shutil.copy(ROOT / "pyproject.toml", where / "pyproject.toml")
    return where


def _edit(path: Path, old: str, new: str) -> str:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path}: the test's anchor moved"
    path.write_text(text.replace(old, new))
    return text


def _fails_after_edit(tree: Path, path: Path, old: str, new: str, error: str) -> None:
    """The type check of `tree` with `old` replaced by `new` in `path` fails, saying `error`
    (a regex); the file is put back whatever happens."""
    before = _edit(path, old, new)
    try:
        out = _mypy(tree)
    finally:
        path.write_text(before)
    assert out.returncode != 0
    assert re.search(error, out.stdout), out.stdout


def test_the_type_check_passes_and_fails_when_the_moment_reads_a_renamed_part(tree_copy):
    ok = _mypy(tree_copy)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    _fails_after_edit(tree_copy, tree_copy / "station" / "daemon" / "supervisor.py",
                      "self.profiles_by_name: dict[str, Profile] =", "self.profile_table: dict[str, Profile] =",
                      r"supervisor\.py:\d+: error: \"Station\" has no attribute \"profiles_by_name\"")
    _fails_after_edit(tree_copy, tree_copy / "station" / "decisions" / "moment.py",
                      "prof = ctx.profiles.get(name)", "prof = ctx._profiles.get(name)",
                      r"moment\.py:\d+: error: \"VerdictContext\" has no attribute \"_profiles\"")


def test_only_what_does_not_exist_reads_as_404_a_bug_stays_a_bug():
    """The facade says "unknown batch" with contracts.types.NotFound; a KeyError from a bug (a
    record read by a key it does not have) must not reach the MES as 404 "not found"."""
    import asyncio

    from fastapi import HTTPException

    from contracts.types import NotFound
    from web.views import call

    def unknown() -> None:
        raise NotFound("unknown batch 7")

    def bug() -> object:
        return {}["verdict"]

    with pytest.raises(HTTPException) as exc:
        asyncio.run(call(unknown))
    assert exc.value.status_code == 404 and exc.value.detail == "unknown batch 7"
    with pytest.raises(KeyError):  # the web app answers it 500 (an internal error), never 404
        asyncio.run(call(bug))
