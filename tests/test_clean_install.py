"""The README's main command works from a clean install of the runtime dependencies alone.

A fresh venv gets `pip install .` (no test extra, not editable, from a copy of the source tree so
nothing of the checkout's own .venv leaks in); then `station demo` from that venv must serve the
operator page and `/api/health` on 127.0.0.1. CI installs the test extra for everything else, which
once hid a runtime import that lived only there (the demo served no page on a fresh clone).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "contracts", "station", "drivers", "db", "web", "cli")

pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str, timeout_s: float = 5.0) -> tuple[int, str]:
    with urllib.request.urlopen(url, timeout=timeout_s) as r:
        return r.status, r.read().decode("utf-8", "replace")


@pytest.fixture(scope="module")
def runtime_venv(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("clean")
    src = work / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build")
    for name in SOURCES:
        p = ROOT / name
        (shutil.copytree(p, src / name, ignore=ignore) if p.is_dir() else shutil.copy2(p, src / name))
    venv = work / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "--disable-pip-version-check", str(src)],
                         capture_output=True, text=True, timeout=900)
    assert pip.returncode == 0, pip.stderr[-3000:]
    return venv


def test_runtime_install_has_no_test_packages(runtime_venv):
    """The venv really is runtime-only: pytest is absent, so nothing passes by accident."""
    r = subprocess.run([str(runtime_venv / "bin" / "python"), "-c", "import pytest"], capture_output=True)
    assert r.returncode != 0


def test_demo_serves_page_and_health_from_runtime_install(runtime_venv, tmp_path):
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["MPLCONFIGDIR"] = str(tmp_path / "mpl")
    proc = subprocess.Popen(
        [str(runtime_venv / "bin" / "station"), "demo", "--no-batch", "--serial", "2", "--can", "1",
         "--port", str(port), "--db", f"sqlite:///{tmp_path / 'demo.db'}"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        status = None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                status, body = _get(base + "/api/health", 2.0)
                break
            except OSError:
                time.sleep(0.5)
        assert proc.poll() is None, f"station demo exited with {proc.returncode}:\n{proc.stdout.read()}"
        assert status == 200, "no answer on /api/health within 120 s"
        assert '"ok"' in body or "ok" in body
        status, page = _get(base + "/")
        assert status == 200 and "<html" in page.lower()
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, _ = proc.communicate()
    # A stop (SIGTERM) ends it cleanly: lamp off, web server stopped, exit 0, no traceback.
    assert proc.returncode == 0 and "Traceback" not in out, out
    # A new user is told where the page is and how to sign in.
    assert f"http://127.0.0.1:{port}/" in out
    assert "demo-operator-token" in out


def test_missing_web_app_is_a_hard_error(tmp_path):
    """Without an importable web app, `station demo` exits non-zero with one clear line.

    The import is made to fail in the child (sys.modules entry None), as on an installation that
    lacks a runtime dependency of web/app.py; the demo must refuse instead of running headless.
    """
    port = _free_port()
    env = dict(os.environ, MPLCONFIGDIR=str(tmp_path / "mpl"))
    code = ("import sys; sys.modules['web.app'] = None; from cli.main import main; "
            f"sys.exit(main(['demo', '--no-batch', '--serial', '1', '--can', '0', '--port', '{port}', "
            f"'--db', 'sqlite:///{tmp_path / 'demo.db'}']))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr[-2000:]
    errors = [line for line in r.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and "operator page cannot be served" in errors[0], r.stderr[-2000:]
    assert "Traceback" not in r.stderr
