"""Shared helpers of the tests/test_db_*.py modules: databases and realistic sample streams."""

from __future__ import annotations

import uuid
from contextlib import contextmanager
from typing import Iterator

import numpy as np

from db import Database
from contracts.types import Segment

PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


# Another PROCESS holding a SQLite database's write lock for argv[2] seconds (a backup tool, an
# engineer's sqlite3 shell): prints "LOCKED <unix time>" once it holds it, "RELEASED <time>" after.
HOLD_LOCK = """
import sqlite3, sys, time
con = sqlite3.connect(sys.argv[1], isolation_level=None, timeout=30)
con.execute("BEGIN EXCLUSIVE")
print("LOCKED", time.time(), flush=True)
time.sleep(float(sys.argv[2]))
con.execute("ROLLBACK")
print("RELEASED", time.time(), flush=True)
"""


def sqlite_db(tmp_path, name: str = "station.db") -> Database:
    db = Database(f"sqlite:///{tmp_path / name}")
    db.upgrade()
    return db


def pg_reachable() -> bool:
    try:
        import psycopg

        with psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=test", connect_timeout=2):
            return True
    except Exception:
        return False


@contextmanager
def pg_database() -> Iterator[str]:
    """A fresh PostgreSQL database for one test (dropped afterwards); yields its URL."""
    import psycopg

    name = f"station_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=test", autocommit=True) as c:
        c.execute(f'CREATE DATABASE "{name}"')
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
    finally:
        with psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=test", autocommit=True) as c:
            c.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def lis3dsh_stream(n: int, seed: int = 0, odr_hz: float = 3.125, t0_s: float = 0.0):
    """Fast-thermal-like LIS3DSH samples: 0.06 mg counts, 1 C temperature steps, lamp heating."""
    rng = np.random.default_rng(seed)
    time_s = t0_s + np.arange(n) / odr_hz
    temp_c = 25.0 + np.round(22.0 * (1 - np.exp(-np.arange(n) / (n / 4))) + rng.normal(0, 0.3, n))
    base = np.array([0.577, 0.577, 0.577]) * np.where(np.arange(n) < n // 2, 1.0, -1.0)[:, None]
    drift = (temp_c - 25.0)[:, None] * np.array([0.4e-3, -0.8e-3, 1.1e-3])
    counts = np.round((base + drift + rng.normal(0, 0.15e-3, (n, 3))) / 60e-6)
    return time_s, counts * 60e-6, temp_c


def adxl355_stream(n: int, seed: int = 1):
    """ADXL355-like: 3.9 ug counts and temperature from -9.05 LSB/C counts (non-decimal values)."""
    rng = np.random.default_rng(seed)
    time_s = np.arange(n) * 0.001 + 12.345678
    acc = np.round(rng.normal(0.3, 0.2, (n, 3)) / 3.9e-6) * 3.9e-6
    temp = 25.0 + (np.round(1885 + rng.normal(0, 50, n)) - 1885) / -9.05
    return time_s, acc, temp


def segment(index: int, t_start_s: float = 0.0, position: int | None = 0) -> Segment:
    return Segment(
        index=index,
        orientation=index % 2,
        n_samples=1000,
        t_start_s=t_start_s,
        t_end_s=t_start_s + 320.0,
        acc_mean_g=(0.577 + index * 1e-4, 0.578, 0.579),
        acc_std_g=(1.5e-4, 1.6e-4, 1.7e-4),
        temp_mean_c=25.0 + index,
        temp_std_c=0.3,
        position=position,
    )


THERMAL_JSON = {
    "serial": "SIM0001",
    "axes_method": "offline",  # the reported axes are the offline fit's, as `station calibrate --json` gives them
    "axes": {"x": {"tdb_mg_per_c": 0.42, "tdsf_ppm_per_c": -120.0, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": 3.0},
             "y": {"tdb_mg_per_c": -0.79, "tdsf_ppm_per_c": -10.0, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": 3.0},
             "z": {"tdb_mg_per_c": 1.09, "tdsf_ppm_per_c": -299.0, "tdb_sigma_mg_per_c": 0.02, "tdsf_sigma_ppm_per_c": 4.0}},
    "streaming": {
        "method": "streaming",
        "n_segments": 4,
        "axes": {
            "x": {"tdb_mg_per_c": 0.41, "tdsf_ppm_per_c": -118.0, "tdsf_clamped": False},
            "y": {"tdb_mg_per_c": -0.8, "tdsf_ppm_per_c": 0.0, "tdsf_clamped": True},
            "z": {"tdb_mg_per_c": 1.1, "tdsf_ppm_per_c": -300.0, "tdsf_clamped": False},
        },
    },
    "offline": {
        "method": "offline",
        "n_segments": 4,
        "axes": {
            "x": {"tdb_mg_per_c": 0.42, "tdsf_ppm_per_c": -120.0, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": 3.0},
            "y": {"tdb_mg_per_c": -0.79, "tdsf_ppm_per_c": -10.0, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": 3.0},
            "z": {"tdb_mg_per_c": 1.09, "tdsf_ppm_per_c": -299.0, "tdb_sigma_mg_per_c": 0.02, "tdsf_sigma_ppm_per_c": 4.0},
        },
    },
}

SFEM_JSON = {  # the SFEM record (contracts/sfem_result.py SfemResult), two steps and a thermal model
    "shape": "sfem-record/1",
    "t_ref_c": 25.0,
    "steps": [
        {"temperature_step": 0, "temp_c": 25.0, "n_positions": 24, "A": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
         "b": [0.01, -0.02, 0.03], "bias": [0.01, -0.02, 0.03], "bias_sigma": [1e-5, 1e-5, 1e-5],
         "scale": [1.0, 1.0, 1.0], "scale_sigma": [1e-5, 1e-5, 1e-5], "rmse_before_mg": 12.0, "rmse_after_mg": 0.9},
        {"temperature_step": 1, "temp_c": 45.0, "n_positions": 24, "A": [[1.001, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.999]],
         "b": [0.011, -0.021, 0.031], "bias": [0.011, -0.021, 0.031], "bias_sigma": [1e-5, 1e-5, 1e-5],
         "scale": [1.001, 1.0, 0.999], "scale_sigma": [1e-5, 1e-5, 1e-5], "rmse_before_mg": 13.0, "rmse_after_mg": 1.0},
    ],
    "thermal": {"degree": 1, "t_ref_c": 25.0, "coef": {"scale": [[1.0, 1.0, 1.0], [1e-5, 0.0, 0.0]]}},
}
