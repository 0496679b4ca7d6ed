"""Design-5.1 fast-thermal logs from a generator that shares nothing with the station's simulator.

The plant is written out here in a dozen lines (first-order plate temperature, the thermal model
of martinez2022 eq. 1 with white noise, P/N orientations per design 3.3's position table), so a
replay of these logs tests the station on data it was not built around. Used by
tests/test_replay.py and benchmarks/replay_rate.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

ODR_HZ = 3.125
S = 1.0 / np.sqrt(3.0)
# (duration s, lamp, position index): P = 0 = (s, s, s), N = 1 = -(s, s, s) (design position table)
SCHEDULE = ((800.0, 0, 0), (1300.0, 1, 0), (1100.0, 1, 1), (1500.0, 0, 1))
RISE_C = 30.0
TAU_S = 300.0


@dataclass
class LogTruth:
    serial: str
    tdb_mg_per_c: np.ndarray  # (3,)
    tdsf_ppm_per_c: np.ndarray  # (3,)
    bias_g: np.ndarray  # (3,)


def generate(serial: str, seed: int, noise_g: float = 2e-4) -> tuple[str, LogTruth]:
    """(CSV text, truth) of one DUT run through SCHEDULE."""
    rng = np.random.default_rng(seed)
    truth = LogTruth(serial, rng.uniform(-1.0, 1.0, 3), rng.uniform(-400.0, -20.0, 3), rng.uniform(-0.03, 0.03, 3))
    dt = 1.0 / ODR_HZ
    t_parts, temp_parts, lamp_parts, pos_parts = [], [], [], []
    t0, temp = 0.0, 25.0
    a = np.exp(-dt / TAU_S)
    for dur, lamp, pos in SCHEDULE:
        n = int(round(dur * ODR_HZ))
        target = 25.0 + RISE_C * lamp
        k = np.arange(1, n + 1)
        tt = target + (temp - target) * a ** k
        t_parts.append(t0 + (k - 1) * dt)
        temp_parts.append(tt)
        lamp_parts.append(np.full(n, lamp))
        pos_parts.append(np.full(n, pos))
        t0 += n * dt
        temp = float(tt[-1])
    t = np.concatenate(t_parts)
    temp_c = np.concatenate(temp_parts) + rng.normal(0.0, 0.01, len(t))
    lamp = np.concatenate(lamp_parts)
    pos = np.concatenate(pos_parts)
    g_dir = np.where(pos[:, None] == 0, S, -S) * np.ones((1, 3))
    d_t = (temp_c - 25.0)[:, None]
    acc = truth.bias_g + truth.tdb_mg_per_c * 1e-3 * d_t + (1.0 + truth.tdsf_ppm_per_c * 1e-6 * d_t) * g_dir
    acc = acc + rng.normal(0.0, noise_g, acc.shape)
    lines = [f"# serial: {serial}", "# sensor: GEN-1", "# profile: fast-thermal", f"# odr_hz: {ODR_HZ}",
             "time_s,ax_g,ay_g,az_g,temp_c,lamp,position"]
    for k in range(len(t)):
        lines.append(f"{t[k]:.6f},{acc[k, 0]:.7f},{acc[k, 1]:.7f},{acc[k, 2]:.7f},{temp_c[k]:.4f},{lamp[k]},{pos[k]}")
    return "\n".join(lines) + "\n", truth


def write_logs(folder: Path, n: int, seed: int = 7) -> tuple[list[Path], list[LogTruth]]:
    folder.mkdir(parents=True, exist_ok=True)
    paths, truths = [], []
    for i in range(n):
        text, truth = generate(f"GEN{i + 1:04d}", seed * 1000 + i)
        p = folder / f"GEN{i + 1:04d}.csv"
        p.write_text(text)
        paths.append(p)
        truths.append(truth)
    return paths, truths
