"""Simulator speed: samples per second of SimWorld.advance and of whole profiles (prints figures).

    .venv/bin/python benchmarks/sim_speed.py
"""

from __future__ import annotations

import time

from drivers.sim.physics import HIDDEN_EFFECTS, draw_population
from drivers.sim.profiles import profile_duration_s, run_profile
from drivers.sim.world import SimWorld


def main() -> None:
    for effects in ((), HIDDEN_EFFECTS):
        label = "all effects" if effects else "no effects"
        w = SimWorld(draw_population(64, 1, effects=effects), seed=1)
        t = time.perf_counter()
        w.advance(10000)
        dt = time.perf_counter() - t
        print(f"advance(10000) x 64 DUTs, {label}: {dt:.3f} s = {64e4 / dt / 1e6:.2f} M samples/s")
        w = SimWorld(draw_population(64, 1, effects=effects), seed=1)
        t = time.perf_counter()
        for _ in range(200):
            w.advance(16)  # a SimStation tick at speed 500 (0.01 s x 500 x 3.125 Hz)
        dt = time.perf_counter() - t
        print(f"200 x advance(16) x 64 DUTs, {label}: {dt / 200 * 1e3:.2f} ms per call = {200 * 16 * 64 / dt / 1e6:.2f} M samples/s")
    for name in ("fast-thermal", "six-position", "sfem-24", "validation"):
        w = SimWorld(draw_population(16, 1, effects=HIDDEN_EFFECTS), seed=1)
        t = time.perf_counter()
        run_profile(w, name)
        dt = time.perf_counter() - t
        print(f"profile {name} ({profile_duration_s(name) / 3600:.1f} h) x 16 DUTs, all effects: {dt:.2f} s")


if __name__ == "__main__":
    main()
