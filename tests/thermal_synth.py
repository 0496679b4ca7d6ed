"""A small synthetic fast-thermal record with known TDB/TDSF, independent of drivers/sim.

martinez2022 eq. 1 per axis, LIS3DSH-like: 3.125 Hz, 0.5 mg noise, 0.06 mg LSB, temperature read
in 1 C steps after ~0.3 C of noise dither; the die follows a lamp-heated plate (exponential
approach), self-heating after power-up, and the plate sits hotter over the lamp after the turn.
Profile: P ambient -> lamp on (P hot) -> turn (N hot) -> lamp off (N ambient).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

S = 1.0 / np.sqrt(3.0)
ODR_HZ = 3.125


@dataclass
class Truth:
    tdb_mg_per_c: np.ndarray
    tdsf_ppm_per_c: np.ndarray
    bias_g: np.ndarray
    scale: np.ndarray


@dataclass
class Record:
    time_s: np.ndarray
    acc_g: np.ndarray
    temp_c: np.ndarray
    truth: Truth
    die_temp_c: np.ndarray
    position: np.ndarray  # 0 P, 1 N, -1 while turning
    phase_starts_s: list[float] = field(default_factory=list)


def _first_order(target: np.ndarray, tau_s: float, dt: float, start: float) -> np.ndarray:
    out = np.empty_like(target)
    a = 1.0 - np.exp(-dt / tau_s)
    y = start
    for i, v in enumerate(target):
        y += a * (v - y)
        out[i] = y
    return out


def fast_thermal(
    seed: int = 0,
    tdb_mg_per_c=(0.8, -0.5, 1.2),
    tdsf_ppm_per_c=(-150.0, -40.0, -300.0),
    ambient_c: float = 24.0,
    lamp_rise_c: float = 30.0,
    turned_extra_c: float = 4.0,
    phases_min=(25.0, 30.0, 25.0, 35.0),
    noise_g: float = 0.5e-3,
    temp_noise_c: float = 0.3,
    turn_s: float = 8.0,
    self_heating_c: float = 3.0,
    extra_steps: int = 0,
    plan: list[tuple[float, int, int]] | None = None,
) -> Record:
    """extra_steps > 0 appends, per extra step, another lamp-on / lamp-off cycle in N.
    plan: [(minutes, lamp 0/1, orientation +1 P / -1 N), ...] replaces the default four phases;
    the plate is turned (over turn_s) at the start of every phase whose orientation differs."""
    rng = np.random.default_rng(seed)
    truth = Truth(
        np.asarray(tdb_mg_per_c, dtype=float),
        np.asarray(tdsf_ppm_per_c, dtype=float),
        rng.normal(0.0, 0.02, 3),
        1.0 + rng.normal(0.0, 0.01, 3),
    )
    dt = 1.0 / ODR_HZ
    # (duration_min, lamp, orientation sign) for each phase
    if plan is None:
        plan = [(phases_min[0], 0, 1), (phases_min[1], 1, 1), (phases_min[2], 1, -1), (phases_min[3], 0, -1)]
        for _ in range(extra_steps):
            plan += [(30.0, 1, -1), (35.0, 0, -1)]
    n_per = [int(round(m * 60 * ODR_HZ)) for m, _, _ in plan]
    n = sum(n_per)
    time_s = np.arange(n) * dt + 12.345
    lamp = np.concatenate([np.full(k, l) for k, (_, l, _) in zip(n_per, plan)])
    sign = np.concatenate([np.full(k, s, dtype=float) for k, (_, _, s) in zip(n_per, plan)])
    starts = np.cumsum([0] + n_per[:-1])
    # each turn: a linear move over turn_s at the start of a phase with the other orientation
    n_turn = int(turn_s * ODR_HZ)
    position = np.where(sign > 0, 0, 1)
    for j in range(1, len(plan)):
        if plan[j][2] != plan[j - 1][2]:
            i_turn = starts[j]
            sign[i_turn : i_turn + n_turn] = np.linspace(plan[j - 1][2], plan[j][2], n_turn + 2)[1:-1]
            position[i_turn : i_turn + n_turn] = -1
    plate_target = ambient_c + lamp * (lamp_rise_c + np.where(sign < 0, turned_extra_c, 0.0))
    plate = _first_order(plate_target, 240.0, dt, ambient_c)
    die = _first_order(plate, 60.0, dt, ambient_c)
    die = die + self_heating_c * (1.0 - np.exp(-(time_s - time_s[0]) / 300.0))
    g_dir = sign[:, None] * S * np.ones(3)
    acc0 = truth.bias_g + truth.scale * g_dir
    d_t = (die - 25.0)[:, None]
    acc = acc0 + d_t * (truth.tdb_mg_per_c * 1e-3 + truth.tdsf_ppm_per_c * 1e-6 * acc0)
    acc = acc + rng.normal(0.0, noise_g, acc.shape)
    acc = np.round(acc / 60e-6) * 60e-6
    temp = np.round(die + rng.normal(0.0, temp_noise_c, n))
    return Record(time_s, acc, temp, truth, die, position, [float(time_s[s]) for s in starts])
