"""Build the board firmware (firmware/, C) on demand, once per checkout, safely from parallel tests.

`build("host")` runs `make -C firmware host` under an exclusive file lock (pytest-xdist workers
and a demo may ask at the same time) and returns the build folder. make itself decides whether
anything is out of date, so a second call costs one make run of a few milliseconds.
"""

from __future__ import annotations

import fcntl
import shutil
import subprocess
from pathlib import Path

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware"
BUILD_DIR = FIRMWARE_DIR / "build"

# make target -> the tools it needs (Debian packages in brackets, scripts/test.sh installs them)
TOOLS = {
    "host": ("cc", "make"),
    "disc": ("arm-none-eabi-gcc", "make"),  # [gcc-arm-none-eabi libnewlib-arm-none-eabi]
    "qemu": ("arm-none-eabi-gcc", "make"),
    "bench": ("arm-none-eabi-gcc", "make"),
}


class FirmwareBuildError(RuntimeError):
    """make failed; the message carries its output."""


def missing_tools(target: str) -> list[str]:
    """Tools the target needs that are not on PATH (empty when it can be built here)."""
    return [t for t in TOOLS.get(target, ("make",)) if shutil.which(t) is None]


def build(target: str = "host") -> Path:
    """Build one make target of firmware/ and return firmware/build/<target>."""
    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    with open(BUILD_DIR / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        proc = subprocess.run(["make", "-C", str(FIRMWARE_DIR), target], capture_output=True, text=True)
    if proc.returncode != 0:
        raise FirmwareBuildError(f"make -C firmware {target} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return BUILD_DIR / target
