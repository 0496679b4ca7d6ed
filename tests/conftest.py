"""Test-run order, and the diagnose cache switched off: the files that take minutes of CPU start first, so parallel workers
(scripts/test.sh runs pytest-xdist with --dist loadfile, which hands out whole files in collection
order) do not end with one worker grinding through an 8-DUT diagnosis while the others idle."""

from __future__ import annotations

import os

# `station diagnose` keeps its ranking in the user's cache folder; a test run must not fill it
# (tests/test_diagnostics_cache.py points it at its own folders)
os.environ.setdefault("STATION_DIAGNOSE_CACHE", "off")

HEAVY_FIRST = (
    "test_fault_matrix.py",
    "test_diagnostics_batch8.py",
    "test_diagnostics_batch8_control.py",
    "test_diagnostics.py",
    "test_diagnostics_effects_realistic.py",
    "test_diagnostics_realistic.py",
    "test_daemon_e2e.py",
    "test_program_verify_e2e.py",
    "test_clean_install.py",
    "test_replay.py",
    "test_replay_line_faults.py",
    "test_replay_line.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(HEAVY_FIRST)))  # stable: keeps file order
