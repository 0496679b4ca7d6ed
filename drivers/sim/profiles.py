"""Open-loop test profiles for `station simulate`: a list of timed steps run on a SimWorld.

The same world code runs behind the simulated boards of `station demo`; here there is no
sequencer, so every step has a fixed duration chosen so that the station's algorithms get what
they need (for fast-thermal: one martinez2022 3.3 segment of 500 discarded + 1000 averaged samples
at 3.125 Hz in each of the four phases, |filtered gradient| < 1 C/min, > 20 C between the two
segments of one orientation).

Profiles:
- fast-thermal: P ambient 14 min (power-up, self-heating), lamp on 25 min, turn to N with the lamp
  on 20 min, lamp off 30 min: 89 min (martinez2022: 60-90 min).
- six-position: each axis up and down (+x, -x, +y, -y, +z, -z); per orientation the chamber steps
  through -10, 7.5, 25, 42.5, 60 C (alternately up and down), ramp 2 C/min, hold 15 min per step
  (martinez2022 4.4 reference test, time-compressed).
- sfem-24: chamber steps -10, 7.5, 25, 42.5, 60 C; at each, 20 min settling then the 24 positions of
  sensors2023 Table 1 (contracts.positions.SFEM24) held 90 s each.
- validation: power-up at 25 C in P held 20 min (self-heating), then one full thermal cycle per
  orientation 25 -> 60 -> -10 -> 25 C with 10 min holds at the extremes and 5 min at 25 C, at
  different chamber ramp rates: P 2, N 1, +x 0.5, -y 2, +z 1, -z 2 C/min. Each cycle has its own
  position, so the `position` column identifies the cycle (held-out folds).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.sim.world import SimWorld
from contracts.logfile import DutLog
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX, POSITION_NAMES, SFEM24, SIX_POSITION
from contracts.types import StationError


@dataclass(frozen=True)
class Step:
    """Controls held for duration_s; chamber_setpoint_c None = room air (no chamber)."""

    duration_s: float
    position: int = 0
    lamp_on: bool = False
    chamber_setpoint_c: float | None = None
    chamber_ramp_c_per_min: float | None = None  # None: the world's current/default ramp rate
    label: str = ""


P, N = POSITION_INDEX["P"], POSITION_INDEX["N"]
CHAMBER_STEPS_C = (-10.0, 7.5, 25.0, 42.5, 60.0)
CHAMBER_RAMP_C_PER_MIN = 2.0


def fast_thermal_steps() -> list[Step]:
    return [
        Step(14 * 60, P, False, label="P ambient"),
        Step(28 * 60, P, True, label="P hot"),  # the slowest of 32 DUTs need ~25.5 min to settle
        Step(20 * 60, N, True, label="N hot"),
        Step(30 * 60, N, False, label="N ambient"),
    ]


def _goto(steps: list[Step], current_c: float, target_c: float, hold_s: float, position: int, ramp: float, label: str) -> float:
    """Ramp the chamber to target_c then hold hold_s (one step: the ramp is the world's rate limit)."""
    ramp_s = abs(target_c - current_c) / ramp * 60.0
    steps.append(Step(ramp_s + hold_s, position, False, target_c, ramp, label))
    return target_c


def six_position_steps(temps_c=CHAMBER_STEPS_C, hold_s: float = 15 * 60, ramp: float = CHAMBER_RAMP_C_PER_MIN) -> list[Step]:
    steps: list[Step] = []
    cur = 25.0
    order = list(temps_c)
    for k, name in enumerate(SIX_POSITION):
        pos = POSITION_INDEX[name]
        seq = order if k % 2 == 0 else order[::-1]
        for t in seq:
            cur = _goto(steps, cur, t, hold_s, pos, ramp, f"{name} {t:g} C")
    return steps


def sfem24_steps(temps_c=CHAMBER_STEPS_C, settle_s: float = 20 * 60, hold_s: float = 90.0, ramp: float = CHAMBER_RAMP_C_PER_MIN) -> list[Step]:
    steps: list[Step] = []
    cur = 25.0
    for t in temps_c:
        first = POSITION_INDEX[SFEM24[0]]
        cur = _goto(steps, cur, t, settle_s, first, ramp, f"settle {t:g} C")
        for name in SFEM24:
            steps.append(Step(hold_s, POSITION_INDEX[name], False, t, ramp, f"{name} {t:g} C"))
    return steps


VALIDATION_CYCLES: tuple[tuple[str, float], ...] = (("P", 2.0), ("N", 1.0), ("+x", 0.5), ("-y", 2.0), ("+z", 1.0), ("-z", 2.0))


def validation_steps(t_hot_c: float = 60.0, t_cold_c: float = -10.0, hold_s: float = 10 * 60) -> list[Step]:
    steps = [Step(20 * 60, P, False, 25.0, 2.0, "power-up P 25 C")]
    cur = 25.0
    for name, rate in VALIDATION_CYCLES:
        pos = POSITION_INDEX[name]
        cur = _goto(steps, cur, t_hot_c, hold_s, pos, rate, f"{name} heat {rate:g} C/min")
        cur = _goto(steps, cur, t_cold_c, hold_s, pos, rate, f"{name} cool {rate:g} C/min")
        cur = _goto(steps, cur, 25.0, 5 * 60, pos, rate, f"{name} heat {rate:g} C/min")
    return steps


PROFILES: dict[str, Callable[[], list[Step]]] = {
    "fast-thermal": fast_thermal_steps,
    "six-position": six_position_steps,
    "sfem-24": sfem24_steps,
    "validation": validation_steps,
}


def profile_steps(name: str) -> list[Step]:
    if name not in PROFILES:
        raise StationError(f"unknown profile {name!r} (known: {', '.join(PROFILES)})")
    return PROFILES[name]()


def profile_duration_s(name: str) -> float:
    return float(sum(s.duration_s for s in profile_steps(name)))


def run_steps(
    world: SimWorld,
    steps: list[Step],
    progress: Callable[[float, float], None] | None = None,
    chunk_samples: int = 4096,
) -> dict[str, np.ndarray]:
    """Run steps on the world; returns the columns of every DUT (counts already in g and C)."""
    n_d = world.n_duts
    odr = world.odr_hz
    counts = [int(round(s.duration_s * odr)) for s in steps]
    total = sum(counts)
    time_s = np.empty(total)
    acc = np.empty((n_d, total, 3), dtype=np.int32)
    temp = np.empty((n_d, total), dtype=np.int32)
    lamp = np.empty(total, dtype=np.int8)
    pos = np.empty(total, dtype=np.int64)
    plate = np.empty(total)
    k = 0
    for step, n in zip(steps, counts):
        world.lamp_on = step.lamp_on
        world.position = step.position
        world.chamber_setpoint_c = step.chamber_setpoint_c
        if step.chamber_ramp_c_per_min is not None:
            world.chamber_ramp_c_per_min = step.chamber_ramp_c_per_min
        left = n
        while left > 0:
            m = min(left, chunk_samples)
            c = world.advance(m)
            time_s[k : k + m] = c.time_s
            acc[:, k : k + m] = c.acc_counts
            temp[:, k : k + m] = c.temp_counts
            plate[k : k + m] = c.plate_temp_c
            lamp[k : k + m] = int(step.lamp_on)
            pos[k : k + m] = step.position
            k += m
            left -= m
            if progress is not None:
                progress(k / odr, total / odr)
    return {"time_s": time_s, "acc_counts": acc, "temp_counts": temp, "lamp": lamp, "position": pos, "plate_temp_c": plate}


def run_profile(
    world: SimWorld,
    name: str,
    progress: Callable[[float, float], None] | None = None,
    meta: dict[str, str] | None = None,
) -> list[DutLog]:
    """Run a named profile open loop on the world; one DutLog per DUT (design 5.1 columns)."""
    steps = profile_steps(name)
    cols = run_steps(world, steps, progress)
    ref = GRAVITY_DIRECTIONS[cols["position"]]
    logs = []
    for i, truth in enumerate(world.duts):
        ident = world.identity(i)
        m = {
            "serial": truth.serial,
            "sensor": truth.sensor,
            "profile": name,
            "seed": str(world.seed),
            "effects": ",".join(truth.effects) or "none",
            "odr_hz": f"{world.odr_hz:g}",
            "fw": ident.fw,
            "ug_per_lsb": f"{ident.ug_per_lsb:g}",
            "source": "simulator",
            "noise": world.noise_models[i].name if hasattr(world, "noise_models") else "white",
        }
        m.update(meta or {})
        logs.append(
            DutLog(
                time_s=cols["time_s"].copy(),
                acc_g=ident.acc_g(cols["acc_counts"][i]),
                temp_c=ident.temp_c(cols["temp_counts"][i]),
                meta=m,
                lamp=cols["lamp"].copy(),
                position=cols["position"].copy(),
                ref_dir=ref.copy(),
            )
        )
    return logs


def step_table(name: str) -> list[dict]:
    """The steps of a profile with their start/end times (for docs, truth.json and diagnostics)."""
    t = 0.0
    out = []
    for s in profile_steps(name):
        out.append(
            {
                "label": s.label,
                "t_start_s": t,
                "t_end_s": t + s.duration_s,
                "position": POSITION_NAMES[s.position],
                "lamp_on": s.lamp_on,
                "chamber_setpoint_c": s.chamber_setpoint_c,
                "chamber_ramp_c_per_min": s.chamber_ramp_c_per_min,
            }
        )
        t += s.duration_s
    return out


__all__ = [
    "Step",
    "PROFILES",
    "VALIDATION_CYCLES",
    "profile_steps",
    "profile_duration_s",
    "run_steps",
    "run_profile",
    "step_table",
]
