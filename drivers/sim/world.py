"""The simulated test station's physical world: plate, lamp, fixture, chamber and the DUTs on it.

One SimWorld holds every DUT of a batch and advances them together, vectorized over DUTs, at the
boards' ODR. Controls (lamp_on, position, chamber_setpoint_c, chamber_ramp_c_per_min) are held
constant within one advance() call; callers change them between calls.

Thermal chain (all first order, discretized exactly per sample with a = exp(-dt/tau), so a chunk
of n samples is the same computation as n chunks of one sample):

    chamber air  -> moves toward the set point at chamber_ramp_c_per_min (rate-limited), or sits
                    at ambient_c when there is no chamber (chamber_setpoint_c is None)
    local plate  -> follows air + lamp_on * lamp_gain * (lamp_rise_c + turned_extra_c if the plate
                    is turned over the lamp), time constant lamp_tau_s (room) or chamber_plate_tau_s
    die          -> follows the local plate with die_tau_s, plus self-heating (first order toward
                    self_heat_c with self_heat_tau_s since power-up at t = 0)
    MEMS         -> the die, or lagging it with tau_s when the hidden `thermal_lag` effect is on

Noise: one np.random.Generator per DUT, consumed in sample order (4 normals per sample), so the
output does not depend on how advance() is chunked. The bias wander of the noise model
(physics.NoiseModel: random walk and flicker; default `realistic`, `white` = none) draws from a
second per-DUT stream, so a `white` world's output is exactly what it was before noise models.

What the DUTs' hidden effects add is drivers/sim/hidden_effects.py; the temperature sensor faults
that tests arm on a board (stick_temp_sensor, temp_sensor_reads) are drivers/sim/sensor_faults.py.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from drivers.sim.hidden_effects import HiddenEffects
from drivers.sim.physics import DEFAULT_NOISE, SENSORS, DutTruth, NoiseModel, noise_model
from drivers.sim.sensor_faults import TempSensorFaults
from contracts.positions import GRAVITY_DIRECTIONS
from contracts.types import T_REF_C, Identity

SIM_FIRMWARE = "sim-1.0"


@dataclass
class EnvConfig:
    """The room, the lamp and the chamber; defaults give martinez2022-like fast-thermal runs."""

    ambient_c: float = 25.0
    lamp_rise_c: float = 32.0  # settled plate rise with the lamp on
    lamp_tau_s: float = 480.0  # plate time constant in room air (lamp heating and cooling)
    turned_extra_c: float = 6.0  # plate hotter over the lamp after the turn (martinez2022 Fig. 8)
    turned_positions: tuple[int, ...] = (1,)  # positions in which the DUTs sit over the lamp (N)
    chamber_ramp_c_per_min: float = 2.0  # default chamber air ramp rate
    chamber_plate_tau_s: float = 150.0  # plate time constant in the chamber's forced air

    def to_json(self) -> dict:
        d = asdict(self)
        d["turned_positions"] = list(self.turned_positions)
        return d


@dataclass
class WorldChunk:
    """Samples of one advance(n): raw counts exactly as the boards would send them."""

    time_s: np.ndarray  # (n,) sample times since the world started
    acc_counts: np.ndarray  # (n_duts, n, 3) int64
    temp_counts: np.ndarray  # (n_duts, n) int64
    plate_temp_c: np.ndarray  # (n,) reference thermometer (nominal plate, lamp gain 1)
    die_temp_c: np.ndarray  # (n_duts, n) true die temperature (what the temp sensor sees, noise-free)
    mems_temp_c: np.ndarray  # (n_duts, n) true MEMS temperature (= die unless thermal_lag)
    lamp_on: bool
    position: int
    chamber_air_c: np.ndarray  # (n,)

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    @staticmethod
    def concat(chunks: list["WorldChunk"]) -> "WorldChunk":
        """Consecutive chunks as one (a turn is advanced sample by sample)."""
        if len(chunks) == 1:
            return chunks[0]
        last = chunks[-1]
        return WorldChunk(
            time_s=np.concatenate([c.time_s for c in chunks]),
            acc_counts=np.concatenate([c.acc_counts for c in chunks], axis=1),
            temp_counts=np.concatenate([c.temp_counts for c in chunks], axis=1),
            plate_temp_c=np.concatenate([c.plate_temp_c for c in chunks]),
            die_temp_c=np.concatenate([c.die_temp_c for c in chunks], axis=1),
            mems_temp_c=np.concatenate([c.mems_temp_c for c in chunks], axis=1),
            lamp_on=last.lamp_on, position=last.position,
            chamber_air_c=np.concatenate([c.chamber_air_c for c in chunks]),
        )


@dataclass(frozen=True)
class PlateTurn:
    """A plate turned by hand: gravity (plate frame) rotates from g_from to g_to at a steady rate
    over duration_s of sample time, starting at t0_s; about their common normal, or, for opposite
    directions (P to N: the plate turned over), about an axis perpendicular to g_from."""

    g_from: np.ndarray
    g_to: np.ndarray
    t0_s: float
    duration_s: float

    def gravity_at(self, time_s: float) -> np.ndarray:
        f = 1.0 if self.duration_s <= 0 else min(max((time_s - self.t0_s) / self.duration_s, 0.0), 1.0)
        a, b = self.g_from / np.linalg.norm(self.g_from), self.g_to / np.linalg.norm(self.g_to)
        angle = float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
        axis = np.cross(a, b)
        if np.linalg.norm(axis) < 1e-9:
            e = np.eye(3)[int(np.argmin(np.abs(a)))]
            axis = np.cross(a, e)
        axis = axis / np.linalg.norm(axis)
        th = f * angle  # Rodrigues' rotation of a about axis by th
        return a * np.cos(th) + np.cross(axis, a) * np.sin(th) + axis * float(axis @ a) * (1.0 - np.cos(th))

    def over(self, time_s: float) -> bool:
        return time_s >= self.t0_s + self.duration_s


def _stack(truths: list[DutTruth], attr: str) -> np.ndarray:
    return np.array([getattr(t, attr) for t in truths], dtype=np.float64)


class SimWorld:
    """All DUTs of a simulated station (see module doc). Deterministic from `seed`."""

    def __init__(self, duts: list[DutTruth], env: EnvConfig | None = None, odr_hz: float | None = None, seed: int = 0,
                 noise: str | NoiseModel = DEFAULT_NOISE) -> None:
        self.duts = list(duts)
        self.noise_name = noise.name if isinstance(noise, NoiseModel) else str(noise)
        self.noise_models = [noise_model(noise, t.sensor) for t in self.duts]
        self.env = env or EnvConfig()
        self.seed = int(seed)
        n = len(self.duts)
        self._odr_hz = float(odr_hz if odr_hz else (SENSORS[self.duts[0].sensor].odr_hz if n else 3.125))
        # controls
        self.lamp_on: bool = False
        self._position: int = 0
        self.turn: PlateTurn | None = None  # a plate being turned by hand (turn_to); position is its end
        self.chamber_setpoint_c: float | None = None
        self.chamber_ramp_c_per_min: float = self.env.chamber_ramp_c_per_min
        # clock
        self._k = 0  # samples since the last ODR change
        self._t0_s = 0.0  # time of sample _k = 0
        # per-DUT constants
        self._A_inv = np.array([np.linalg.inv(t.A) for t in self.duts]).reshape(n, 3, 3)
        self._bias = _stack(self.duts, "bias_g").reshape(n, 3)
        self._tdb = _stack(self.duts, "tdb_mg_per_c").reshape(n, 3) * 1e-3
        self._tdsf = _stack(self.duts, "tdsf_ppm_per_c").reshape(n, 3) * 1e-6
        self._noise = _stack(self.duts, "noise_g").reshape(n)
        self._tnoise = _stack(self.duts, "temp_noise_c").reshape(n)
        self._lsb_g = _stack(self.duts, "ug_per_lsb").reshape(n) * 1e-6
        self._t_lsb_per_c = _stack(self.duts, "t_lsb_per_c").reshape(n)
        self._t_lsb_at_25 = _stack(self.duts, "t_lsb_at_25c").reshape(n)
        specs = [SENSORS[t.sensor] for t in self.duts]
        self._acc_lim = np.array([s.acc_count_limits for s in specs], dtype=np.int64).reshape(n, 2)
        self._t_lim = np.array([s.temp_count_limits for s in specs], dtype=np.int64).reshape(n, 2)
        self._die_tau = _stack(self.duts, "die_tau_s").reshape(n)
        self._sh_c = _stack(self.duts, "self_heat_c").reshape(n)
        self._sh_tau = _stack(self.duts, "self_heat_tau_s").reshape(n)
        self._lamp_gain = np.append(_stack(self.duts, "lamp_gain").reshape(n), 1.0)  # last: reference
        self._rngs = [np.random.default_rng([self.seed, i, 0x0015E]) for i in range(n)]
        self._bias_rngs = [np.random.default_rng([self.seed, i, 0xB1A5]) for i in range(n)]
        self._rw = np.zeros((n, 3))  # bias random walk state, g
        # Gauss-Markov states (g), started in their stationary distribution
        self._fl = [np.random.default_rng([self.seed, i, 0xB1A6]).standard_normal((3, len(m.flicker_tau_s)))
                    * (m.flicker_g / np.sqrt(max(1, len(m.flicker_tau_s)))) for i, m in enumerate(self.noise_models)]
        # thermal state
        amb = self.env.ambient_c
        self._air = amb
        self._plate = np.full(n + 1, amb)  # per DUT local plate, last = reference thermometer
        self._die_lag = np.full(n, amb)  # die without self-heating
        self._mems = np.full(n, amb)
        self._die_prev = np.full(n, amb)
        self._heat = np.zeros(n)  # self-heating of the die above the plate (all powered up at t = 0)
        self._t_on = np.zeros(n)
        self._effects = HiddenEffects(self.duts)  # as arrays over DUTs (zeros where off)
        self._temp_faults = TempSensorFaults(n)  # armed by tests (stick_temp_sensor, temp_sensor_reads)

    # --- properties ---------------------------------------------------------------------------
    @property
    def n_duts(self) -> int:
        return len(self.duts)

    @property
    def odr_hz(self) -> float:
        return self._odr_hz

    @odr_hz.setter
    def odr_hz(self, hz: float) -> None:
        """Change the sample rate from now on (every board of the world shares one clock)."""
        hz = float(hz)
        if hz <= 0:
            raise ValueError("ODR must be positive")
        self._t0_s = self.time_s
        self._k = 0
        self._odr_hz = hz

    @property
    def time_s(self) -> float:
        """Time of the next sample."""
        return self._t0_s + self._k / self._odr_hz

    @property
    def plate_temp_c(self) -> float:
        """Reference thermometer on the plate (nominal place, lamp gain 1)."""
        return float(self._plate[-1])

    @property
    def chamber_air_c(self) -> float:
        return float(self._air)

    @property
    def die_temp_c(self) -> np.ndarray:
        """True die temperature of every DUT now (noise-free)."""
        return self._die_prev.copy()

    def identity(self, i: int) -> Identity:
        t = self.duts[i]
        return Identity(
            serial=t.serial,
            sensor=t.sensor,
            fw=SIM_FIRMWARE,
            ug_per_lsb=t.ug_per_lsb,
            t_lsb_per_c=t.t_lsb_per_c,
            t_lsb_at_25c=t.t_lsb_at_25c,
            odr_hz=self._odr_hz,
        )

    def power_cycle(self, i: int, off_s: float = 0.0) -> None:
        """Board i powers up again now, after having been off for off_s (no simulated time passes).

        The warm-up transient of the hidden `self_heating` effect starts over; the die's own
        self-heating has decayed by exp(-off_s / self_heat_tau_s) (math.inf: a cold start).
        """
        self._t_on[i] = self.time_s
        self._heat[i] *= float(np.exp(-float(off_s) / self._sh_tau[i]))

    # --- temperature sensor faults (armed by tests) -------------------------------------------
    def stick_temp_sensor(self, i: int, from_s: float | None = None) -> None:
        """DUT i's temperature sensor sticks from sample time from_s (default: the next sample) at
        its reading just before: its board reports that count ever after (a serial board and a CAN
        board alike: both send the counts made here). The die and the MEMS go on heating."""
        self._temp_faults.arm(i, self.time_s if from_s is None else float(from_s), None)

    def temp_sensor_reads(self, i: int, temp_c: float, from_s: float | None = None) -> None:
        """DUT i's temperature sensor reads temp_c (as counts, clipped to the sensor's word) from
        sample time from_s (default: the next sample) on, whatever the die's temperature."""
        tc = np.rint((float(temp_c) - T_REF_C) * self._t_lsb_per_c[i] + self._t_lsb_at_25[i])
        count = int(np.clip(tc, *self._t_lim[i]))
        self._temp_faults.arm(i, self.time_s if from_s is None else float(from_s), count)

    def heal_temp_sensor(self, i: int) -> None:
        """DUT i's temperature sensor reads the die again from the next sample on."""
        self._temp_faults.heal(i)

    # --- stepping -----------------------------------------------------------------------------
    def _air_series(self, n: int, dt: float) -> np.ndarray:
        """Chamber air at each sample of the chunk (rate-limited toward the set point)."""
        sp = self.chamber_setpoint_c
        if sp is None:
            self._air = self.env.ambient_c
            return np.full(n, self._air)
        step = abs(float(self.chamber_ramp_c_per_min or 0.0)) * dt / 60.0
        out = np.empty(n)
        air = self._air
        if step <= 0.0:  # no ramp limit: the air jumps to the set point
            air = float(sp)
            out.fill(air)
        else:
            for k in range(n):
                d = sp - air
                if d == 0.0:
                    out[k:] = air
                    break
                air = sp if abs(d) <= step else air + (step if d > 0 else -step)
                out[k] = air
        self._air = float(air)
        return out

    @property
    def position(self) -> int:
        """The plate's position index (the end of a turn in progress)."""
        return self._position

    @position.setter
    def position(self, value: int) -> None:
        """Put the plate there at once (a fixture's move ends, a test sets it): no turn goes on."""
        self._position = int(value)
        self.turn = None

    def gravity(self) -> np.ndarray:
        """The plate's gravity direction now (nominal, plate frame): mid-turn, where the turn is."""
        if self.turn is not None:
            return self.turn.gravity_at(self.time_s)
        return GRAVITY_DIRECTIONS[int(self.position)].copy()

    def turn_to(self, position: int, duration_s: float) -> None:
        """A person turns the plate to `position` over duration_s of sample time, from where it is
        now (mid-turn too: a turn back starts where the hands are)."""
        g_from = self.gravity()
        self._position = int(position)
        self.turn = PlateTurn(g_from, GRAVITY_DIRECTIONS[int(position)].copy(), self.time_s, max(0.0, float(duration_s)))

    def advance(self, n: int) -> WorldChunk:
        """Step n samples at the ODR with the current controls; returns raw counts per DUT. While
        the plate is being turned, sample by sample along the turn."""
        n = int(n)
        if self.turn is None or n <= 0:
            return self._advance(n, None)
        chunks = []
        while n > 0 and self.turn is not None:
            if self.turn.over(self.time_s):
                self.turn = None
                break
            chunks.append(self._advance(1, self.turn.gravity_at(self.time_s)))
            n -= 1
        if n > 0:
            chunks.append(self._advance(n, None))
        return WorldChunk.concat(chunks)

    def _advance(self, n: int, gravity: np.ndarray | None) -> WorldChunk:
        n = int(n)
        nd = self.n_duts
        dt = 1.0 / self._odr_hz
        k = self._k + np.arange(n)
        time_s = self._t0_s + k / self._odr_hz
        self._k += n
        pos = int(self.position)
        g = GRAVITY_DIRECTIONS[pos] if gravity is None else gravity

        # thermal chain -----------------------------------------------------------------------
        air = self._air_series(n, dt)
        in_chamber = self.chamber_setpoint_c is not None
        tau_p = self.env.chamber_plate_tau_s if in_chamber else self.env.lamp_tau_s
        lamp_c = 0.0
        if self.lamp_on:
            lamp_c = self.env.lamp_rise_c + (self.env.turned_extra_c if pos in self.env.turned_positions else 0.0)
        target = air[None, :] + (lamp_c * self._lamp_gain)[:, None]  # (nd+1, n)
        plate, self._plate = _first_order(target, self._plate, np.full(nd + 1, tau_p), dt)
        die_lag, self._die_lag = _first_order(plate[:nd], self._die_lag, self._die_tau, dt)
        since_on = np.maximum(time_s[None, :] - self._t_on[:, None], 0.0)
        heat, self._heat = _first_order(np.repeat(self._sh_c[:, None], n, axis=1), self._heat, self._sh_tau, dt)
        die = die_lag + heat  # (nd, n)
        fx = self._effects.fx
        if "thermal_lag" in self._effects.has:
            lag = np.where(fx["lag_tau"] > 0, fx["lag_tau"], 1e-9)
            mems, self._mems = _first_order(die, self._mems, lag, dt)
            mems = np.where((fx["lag_tau"] > 0)[:, None], mems, die)
            self._mems = np.where(fx["lag_tau"] > 0, self._mems, die[:, -1] if n else self._mems)
        else:
            mems = die
            if n:
                self._mems = die[:, -1].copy()

        # acceleration ------------------------------------------------------------------------
        acc0 = self._bias + self._A_inv @ g  # (nd, 3)
        dT = (mems - T_REF_C)[:, :, None]  # (nd, n, 1)
        acc = acc0[:, None, :] + dT * (self._tdb + self._tdsf * acc0)[:, None, :]
        if self._effects.has:
            acc += self._effects.acceleration(acc0, dT, die, self._die_prev, since_on, n)
        if n:
            self._die_prev = die[:, -1].copy()

        # noise and quantization (per-DUT streams, sample order) ------------------------------
        acc_counts = np.empty((nd, n, 3), dtype=np.int64)
        temp_counts = np.empty((nd, n), dtype=np.int64)
        for i in range(nd):
            z = self._rngs[i].standard_normal((n, 4))
            a = acc[i] + z[:, :3] * (self._noise[i] * self.noise_models[i].white_scale)
            if not self.noise_models[i].is_white:
                a = a + self._bias_wander(i, n, dt)
            acc_counts[i] = np.clip(np.rint(a / self._lsb_g[i]), *self._acc_lim[i]).astype(np.int64)
            t = die[i] + z[:, 3] * self._tnoise[i]
            tc = np.rint((t - T_REF_C) * self._t_lsb_per_c[i] + self._t_lsb_at_25[i])
            temp_counts[i] = np.clip(tc, *self._t_lim[i]).astype(np.int64)
            self._temp_faults.apply(i, time_s, temp_counts[i])
        return WorldChunk(
            time_s=time_s,
            acc_counts=acc_counts,
            temp_counts=temp_counts,
            plate_temp_c=plate[-1].copy(),
            die_temp_c=die,
            mems_temp_c=mems,
            lamp_on=bool(self.lamp_on),
            position=pos,
            chamber_air_c=air,
        )

    def _bias_wander(self, i: int, n: int, dt: float) -> np.ndarray:
        """(n, 3) bias of DUT i in g: random walk + flicker (sum of Gauss-Markov), state carried over."""
        m = self.noise_models[i]
        k = len(m.flicker_tau_s)
        z = self._bias_rngs[i].standard_normal((n, 3 * (1 + k)))
        rw = self._rw[i] + np.cumsum(z[:, :3] * (m.bias_rw_g_per_sqrt_s * np.sqrt(dt)), axis=0)
        self._rw[i] = rw[-1]
        out = rw
        if m.flicker_g > 0 and k:
            sig = m.flicker_g / np.sqrt(k)
            for c, tau in enumerate(m.flicker_tau_s):
                a = float(np.exp(-dt / tau))
                u = z[:, 3 * (1 + c):3 * (2 + c)] * (sig * np.sqrt(1.0 - a * a))
                y, _ = lfilter([1.0], [1.0, -a], u, axis=0, zi=(a * self._fl[i][:, c])[None, :])
                self._fl[i][:, c] = y[-1]
                out = out + y
        return out


def lfilter(b, a, x, axis: int = -1, zi=None):
    """scipy.signal.lfilter, imported when first called: scipy.signal takes ~0.7 s to import, which
    every command that only names the simulator's profiles (`station --help`) would pay."""
    from scipy.signal import lfilter as _lfilter

    return _lfilter(b, a, x, axis=axis, zi=zi)


def _first_order(x: np.ndarray, y0: np.ndarray, tau_s: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """y_k = a y_{k-1} + (1 - a) x_k per row, a = exp(-dt/tau): exact for an input held over each
    sample interval. Rows are independent (one tau each). Returns (y, last y)."""
    n = x.shape[1]
    if n == 0:
        return x.copy(), y0.copy()
    a = np.exp(-dt / np.asarray(tau_s, dtype=np.float64))
    y = np.empty_like(x)
    for ua in np.unique(a):  # lfilter wants one coefficient set; DUTs share few distinct taus anyway
        rows = np.nonzero(a == ua)[0]
        zi = (ua * y0[rows])[:, None]
        y[rows], _ = lfilter([1.0 - ua], [1.0, -ua], x[rows], axis=1, zi=zi)
    return y, y[:, -1].copy()


__all__ = ["EnvConfig", "SimWorld", "WorldChunk", "SIM_FIRMWARE"]
