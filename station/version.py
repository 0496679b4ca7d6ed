"""The station software's version, as stored with every run it measures (dut_run.software_version)
and printed on the certificate: the installed package's version (pyproject.toml), read once.

A source tree that is not installed has no version to read: "" then (stored as NULL, "not known"),
never a guess.
"""

from __future__ import annotations

from functools import lru_cache

DIST_NAME = "thermal-cal-station"


@lru_cache(maxsize=1)
def software_version() -> str:
    """The installed station package's version ('' when it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DIST_NAME)
    except PackageNotFoundError:
        return ""


__all__ = ["software_version", "DIST_NAME"]
