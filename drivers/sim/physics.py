"""DUT physics of a simulated accelerometer board (design 6): the hidden truth of one DUT.

Forward model, per DUT and sample (what world.py evaluates, vectorized):

    g_s   nominal gravity of the fixture position (contracts/positions.py), in g
    Acc0  = b + inv(A) g_s                 raw reading at 25 C; A = M C S (sensors2023 eq. 1)
    dT    = T_mems - 25
    Acc   = Acc0 + dT (TDB + TDSF Acc0)    martinez2022 eq. 1, per axis
            + hidden effects (off unless switched on by name, see HIDDEN_EFFECTS)
            + white noise + bias wander (NoiseModel: random walk, flicker; `white` = none),
            then quantized to the sensor's LSB and clipped to its range
    temp  = T_die + noise, quantized to the temperature sensor's resolution

The die temperature T_die = plate lagged by die_tau_s + self-heating after power-up
(self_heat_c (1 - exp(-(t - t_on)/self_heat_tau_s))); the temperature sensor sees it. T_mems is
T_die unless the hidden `thermal_lag` effect makes the MEMS lag the die.

Every parameter is drawn deterministically from a seed; the base parameters of a DUT do not depend
on which hidden effects are switched on (each effect draws from its own stream), so a run with and
without an effect differs by that effect only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from contracts.types import T_REF_C, StationError


@dataclass(frozen=True)
class SensorSpec:
    """Datasheet numbers of a sensor model, as the board reports them (design 3.1 identity)."""

    name: str
    ug_per_lsb: float
    adc_bits: int  # signed output word width
    t_lsb_per_c: float
    t_lsb_at_25c: float
    t_bits: int
    t_signed: bool
    odr_hz: float  # board default output data rate
    noise_g: float  # white noise per sample at the default ODR, 1 sigma
    temp_noise_c: float  # temperature sensor noise before quantization, 1 sigma
    bias_sigma_g: float  # zero-g offset spread, 1 sigma (clipped at 2 sigma)

    @property
    def acc_count_limits(self) -> tuple[int, int]:
        half = 1 << (self.adc_bits - 1)
        return -half, half - 1

    @property
    def temp_count_limits(self) -> tuple[int, int]:
        if self.t_signed:
            half = 1 << (self.t_bits - 1)
            return -half, half - 1
        return 0, (1 << self.t_bits) - 1

    @property
    def temp_resolution_c(self) -> float:
        return 1.0 / abs(self.t_lsb_per_c)


SENSORS: dict[str, SensorSpec] = {
    # ST LIS3DSH at +-2 g: 0.06 mg/digit, 16-bit; OUT_T 8-bit two's complement, 1 LSB/C, 0 = 25 C.
    # Noise: ~150 ug/sqrt(Hz) datasheet; at the 3.125 Hz ODR ~0.5 mg rms per sample.
    "LIS3DSH": SensorSpec("LIS3DSH", 60.0, 16, 1.0, 0.0, 8, True, 3.125, 0.5e-3, 0.3, 0.040),
    # ADI ADXL355 at +-2 g: 3.9 ug/LSB, 20-bit; 12-bit temperature, -9.05 LSB/C, 1885 LSB at 25 C.
    # Noise density 25 ug/sqrt(Hz): at 3.125 Hz (bandwidth ~ODR/2) ~31 ug rms per sample.
    "ADXL355": SensorSpec("ADXL355", 3.9, 20, -9.05, 1885.0, 12, False, 3.125, 25e-6 * math.sqrt(3.125 / 2.0), 0.05, 0.030),
}

@dataclass(frozen=True)
class NoiseModel:
    """Noise of the acceleration output beyond the datasheet's white noise (a named, documented model).

    Real MEMS accelerometers are not white: their Allan deviation falls as 1/sqrt(tau) (white noise),
    flattens at the bias instability (flicker, 1/f) and rises again as sqrt(tau) (bias random walk).
    The bias wander is what makes "independent" 10-minute chunks of a log correlated, so the
    diagnostics must be tested against it. Per axis and DUT:

        bias(t) = rw(t) + flicker(t)
        rw:      random walk, increments N(0, bias_rw_g_per_sqrt_s^2 dt) per sample (starts at 0)
        flicker: sum of first-order Gauss-Markov processes with time constants flicker_tau_s, each of
                 variance flicker_g^2 / len(flicker_tau_s): a flat (1/f-like) Allan deviation of the
                 order of flicker_g between the shortest and longest time constant

    Parameters are orders of magnitude from datasheets and published Allan-deviation plots, not a
    particular part's measurement: LIS3DSH-class (consumer, 0.5 mg white per sample at 3.125 Hz):
    bias instability ~40 ug, random walk 2 ug per sample at 3.125 Hz (3.5 ug/sqrt(s): ~0.2 mg after
    an hour, ~0.8 mg after 15 h); ADXL355-class (low-noise): bias instability ~5 ug, random walk
    ~0.5 ug/sqrt(s). `white` is the ideal part (datasheet white noise only) for unit tests.
    """

    name: str
    bias_rw_g_per_sqrt_s: float = 0.0
    flicker_g: float = 0.0
    flicker_tau_s: tuple[float, ...] = (60.0, 600.0, 6000.0)
    white_scale: float = 1.0  # multiplies the DUT's datasheet white noise
    note: str = ""

    @property
    def is_white(self) -> bool:
        return self.bias_rw_g_per_sqrt_s == 0.0 and self.flicker_g == 0.0

    def to_json(self) -> dict:
        return {"name": self.name, "bias_rw_g_per_sqrt_s": self.bias_rw_g_per_sqrt_s, "flicker_g": self.flicker_g,
                "flicker_tau_s": list(self.flicker_tau_s), "white_scale": self.white_scale, "note": self.note}


NOISE_MODELS: dict[str, NoiseModel] = {
    "white": NoiseModel("white", note="ideal part: the datasheet's white noise only (unit tests)"),
    "lis3dsh": NoiseModel("lis3dsh", bias_rw_g_per_sqrt_s=2e-6 * math.sqrt(3.125), flicker_g=40e-6,
                          note="LIS3DSH-class consumer MEMS: white + 40 ug bias instability + 2 ug/sample "
                               "random walk at 3.125 Hz"),
    "adxl355": NoiseModel("adxl355", bias_rw_g_per_sqrt_s=0.5e-6, flicker_g=5e-6,
                          note="ADXL355-class low-noise MEMS: white + 5 ug bias instability + 0.5 ug/sqrt(s) "
                               "random walk"),
}
# `realistic` (the default of simulated boards and logs) picks the model of the DUT's sensor class.
REALISTIC_BY_SENSOR = {"LIS3DSH": "lis3dsh", "ADXL355": "adxl355"}
NOISE_NAMES: tuple[str, ...] = ("realistic",) + tuple(NOISE_MODELS)
DEFAULT_NOISE = "realistic"


def noise_model(name: str | NoiseModel, sensor: str = "LIS3DSH") -> NoiseModel:
    """Resolve a noise model name (or pass a NoiseModel through); `realistic` depends on the sensor."""
    if isinstance(name, NoiseModel):
        return name
    key = str(name).lower()
    if key == "realistic":
        key = REALISTIC_BY_SENSOR.get(sensor, "lis3dsh")
    if key not in NOISE_MODELS:
        raise StationError(f"unknown noise model {name!r} (known: {', '.join(NOISE_NAMES)})")
    return NOISE_MODELS[key]


HIDDEN_EFFECTS: tuple[str, ...] = (
    "bias_t2",
    "bias_t3",
    "scale_t2",
    "thermal_lag",
    "hysteresis",
    "self_heating",
    "cross_axis",
    "scale_nonlinearity",
)

# Physics notes of the hidden effects (the terms added to Acc, per axis i; dT = T_mems - 25 C).
EFFECT_NOTES: dict[str, str] = {
    "bias_t2": "+ c2_mg_per_c2 * dT^2 (quadratic bias drift)",
    "bias_t3": "+ c3_mg_per_c3 * dT^3 (cubic bias drift)",
    "scale_t2": "+ k2_ppm_per_c2 * dT^2 * Acc0 (quadratic scale drift)",
    "thermal_lag": "the MEMS temperature lags the die (temperature sensor) with tau_s; dT uses T_mems",
    "hysteresis": "+ h_mg * z, z' = (sign(dT_die/dt) - z) |dT_die/dt| / width_c (play-type, rate-independent)",
    "self_heating": "+ w_mg * exp(-(t - t_power_on)/tau_s), warm-up transient not seen by the temperature sensor",
    "cross_axis": "+ dT * sum_{j!=i} x_ppm_per_c[i][j] * Acc0_j (thermal cross-axis coupling)",
    "scale_nonlinearity": "+ dT * n_ppm_per_c_per_g[i] * Acc0_i^2 (drift of the 2nd-order nonlinearity)",
}


def rotation_matrix(angles_rad: np.ndarray) -> np.ndarray:
    """M = Rz(psi) Ry(theta) Rx(phi) from the three small mounting angles (phi, theta, psi)."""
    phi, theta, psi = (float(a) for a in angles_rad)
    cx, sx, cy, sy, cz, sz = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta), math.cos(psi), math.sin(psi)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def nonorthogonality_matrix(alphas_rad: np.ndarray) -> np.ndarray:
    """C = [[1,0,0],[a_yx,1,0],[a_zx,a_zy,1]] (sensors2023 eq. 1), alphas = (a_yx, a_zx, a_zy)."""
    a_yx, a_zx, a_zy = (float(a) for a in alphas_rad)
    return np.array([[1.0, 0.0, 0.0], [a_yx, 1.0, 0.0], [a_zx, a_zy, 1.0]])


def _arr(x, shape=None) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    return a.reshape(shape) if shape is not None else a


@dataclass
class DutTruth:
    """Every true parameter of one simulated DUT (units in the names).

    A (= M C S) maps a raw reading after bias removal to the true acceleration in g:
    g = A (raw - b); the raw reading at 25 C is Acc0 = b + inv(A) g.
    """

    serial: str
    sensor: str
    bias_g: np.ndarray  # (3,) b, zero-g offset at 25 C
    misalignment_deg: np.ndarray  # (3,) mounting rotation angles (phi_x, theta_y, psi_z)
    nonorthogonality_deg: np.ndarray  # (3,) (alpha_yx, alpha_zx, alpha_zy)
    scale: np.ndarray  # (3,) diagonal of S (raw -> g; 1.02 means the axis reads 2 % low)
    tdb_mg_per_c: np.ndarray  # (3,)
    tdsf_ppm_per_c: np.ndarray  # (3,)
    noise_g: float  # white noise per sample, 1 sigma
    temp_noise_c: float  # temperature sensor noise before quantization, 1 sigma
    temp_resolution_c: float  # temperature sensor step
    ug_per_lsb: float
    t_lsb_per_c: float
    t_lsb_at_25c: float
    die_tau_s: float  # die lags the local plate temperature
    self_heat_c: float  # die rise above the plate after power-up, settled
    self_heat_tau_s: float
    lamp_gain: float  # this DUT's share of the lamp heating (its place on the plate), ~1
    effects: dict[str, dict] = field(default_factory=dict)  # enabled hidden effects -> parameters

    def __post_init__(self) -> None:
        for name in ("bias_g", "misalignment_deg", "nonorthogonality_deg", "scale", "tdb_mg_per_c", "tdsf_ppm_per_c"):
            setattr(self, name, _arr(getattr(self, name), (3,)))
        unknown = [e for e in self.effects if e not in HIDDEN_EFFECTS]
        if unknown:
            raise StationError(f"unknown hidden effect(s) {', '.join(unknown)} (known: {', '.join(HIDDEN_EFFECTS)})")

    # --- SFEM factors -------------------------------------------------------------------------
    @property
    def misalignment(self) -> np.ndarray:
        """M, the mounting rotation (3x3)."""
        return rotation_matrix(np.radians(self.misalignment_deg))

    @property
    def nonorthogonality(self) -> np.ndarray:
        """C, lower triangular (3x3)."""
        return nonorthogonality_matrix(np.radians(self.nonorthogonality_deg))

    @property
    def scale_matrix(self) -> np.ndarray:
        return np.diag(self.scale)

    @property
    def A(self) -> np.ndarray:
        """A = M C S: raw (after bias removal) -> true acceleration in g."""
        return self.misalignment @ self.nonorthogonality @ self.scale_matrix

    @property
    def spec(self) -> SensorSpec:
        return SENSORS[self.sensor]

    def acc0_g(self, gravity_g: np.ndarray) -> np.ndarray:
        """Raw reading at 25 C (no drift, no noise) for true accelerations gravity_g (..., 3)."""
        g = np.asarray(gravity_g, dtype=np.float64)
        return self.bias_g + g @ np.linalg.inv(self.A).T

    def effect(self, name: str) -> dict | None:
        return self.effects.get(name)

    # --- JSON ---------------------------------------------------------------------------------
    def to_json(self) -> dict:
        """Plain JSON (lists and floats), including the derived matrices for the validators."""
        out = {
            "serial": self.serial,
            "sensor": self.sensor,
            "bias_g": self.bias_g.tolist(),
            "bias_mg": (self.bias_g * 1e3).tolist(),
            "A": self.A.tolist(),
            "misalignment": self.misalignment.tolist(),
            "misalignment_deg": self.misalignment_deg.tolist(),
            "nonorthogonality": self.nonorthogonality.tolist(),
            "nonorthogonality_deg": self.nonorthogonality_deg.tolist(),
            "scale": self.scale.tolist(),
            "tdb_mg_per_c": self.tdb_mg_per_c.tolist(),
            "tdsf_ppm_per_c": self.tdsf_ppm_per_c.tolist(),
            "noise_g": self.noise_g,
            "temp_noise_c": self.temp_noise_c,
            "temp_resolution_c": self.temp_resolution_c,
            "ug_per_lsb": self.ug_per_lsb,
            "t_lsb_per_c": self.t_lsb_per_c,
            "t_lsb_at_25c": self.t_lsb_at_25c,
            "die_tau_s": self.die_tau_s,
            "self_heat_c": self.self_heat_c,
            "self_heat_tau_s": self.self_heat_tau_s,
            "lamp_gain": self.lamp_gain,
            "effects": {name: _jsonable(params) for name, params in self.effects.items()},
        }
        return out

    @classmethod
    def from_json(cls, d: dict) -> "DutTruth":
        """Inverse of to_json (derived keys A, misalignment, nonorthogonality, bias_mg are ignored)."""
        return cls(
            serial=d["serial"],
            sensor=d["sensor"],
            bias_g=d["bias_g"],
            misalignment_deg=d["misalignment_deg"],
            nonorthogonality_deg=d["nonorthogonality_deg"],
            scale=d["scale"],
            tdb_mg_per_c=d["tdb_mg_per_c"],
            tdsf_ppm_per_c=d["tdsf_ppm_per_c"],
            noise_g=float(d["noise_g"]),
            temp_noise_c=float(d["temp_noise_c"]),
            temp_resolution_c=float(d["temp_resolution_c"]),
            ug_per_lsb=float(d["ug_per_lsb"]),
            t_lsb_per_c=float(d["t_lsb_per_c"]),
            t_lsb_at_25c=float(d["t_lsb_at_25c"]),
            die_tau_s=float(d["die_tau_s"]),
            self_heat_c=float(d["self_heat_c"]),
            self_heat_tau_s=float(d["self_heat_tau_s"]),
            lamp_gain=float(d.get("lamp_gain", 1.0)),
            effects={k: dict(v) for k, v in d.get("effects", {}).items()},
        )


def _jsonable(params: dict) -> dict:
    return {k: (np.asarray(v).tolist() if isinstance(v, (np.ndarray, list, tuple)) else float(v)) for k, v in params.items()}


def _draw_effect(name: str, rng: np.random.Generator) -> dict:
    """Parameters of one hidden effect: clearly above the noise on a validation run, not absurd."""
    def signed(lo: float, hi: float, n: int = 3) -> list[float]:
        return (rng.uniform(lo, hi, n) * rng.choice([-1.0, 1.0], n)).tolist()

    if name == "bias_t2":  # 0.005-0.015 mg/C^2: 6-18 mg at dT = 35 C
        return {"c2_mg_per_c2": signed(0.005, 0.015)}
    if name == "bias_t3":  # 1-3e-4 mg/C^3: 4-13 mg at dT = +-35 C
        return {"c3_mg_per_c3": signed(1e-4, 3e-4)}
    if name == "scale_t2":  # 3-8 ppm/C^2: 4-10 mg at 1 g and dT = 35 C
        return {"k2_ppm_per_c2": signed(3.0, 8.0)}
    if name == "thermal_lag":  # the MEMS lags the temperature sensor by 60-120 s
        return {"tau_s": float(rng.uniform(60.0, 120.0))}
    if name == "hysteresis":  # +-2-3 mg between heating and cooling, saturating over ~4 C
        return {"h_mg": signed(2.0, 3.0), "width_c": float(rng.uniform(3.0, 5.0))}
    if name == "self_heating":  # 3-8 mg warm-up transient, 3-6 min
        return {"w_mg": signed(3.0, 8.0), "tau_s": float(rng.uniform(180.0, 360.0))}
    if name == "cross_axis":  # 100-300 ppm/C of the other axes: 3.5-10 mg at 1 g, dT = 35 C
        x = np.array(signed(100.0, 300.0, 9)).reshape(3, 3)
        np.fill_diagonal(x, 0.0)
        return {"x_ppm_per_c": x.tolist()}
    if name == "scale_nonlinearity":  # 100-300 ppm/C/g: 3.5-10 mg at 1 g, dT = 35 C
        return {"n_ppm_per_c_per_g": signed(100.0, 300.0)}
    raise StationError(f"unknown hidden effect {name!r} (known: {', '.join(HIDDEN_EFFECTS)})")


def check_effects(effects) -> tuple[str, ...]:
    """Validate effect names (user input); StationError names the bad one."""
    names = tuple(effects or ())
    for name in names:
        if name not in HIDDEN_EFFECTS:
            raise StationError(f"unknown hidden effect {name!r} (known: {', '.join(HIDDEN_EFFECTS)})")
    return tuple(e for e in HIDDEN_EFFECTS if e in names)  # canonical order, no duplicates


def draw_population(
    n: int,
    seed: int,
    sensor: str = "LIS3DSH",
    effects=(),
    serial_prefix: str = "SIM",
) -> list[DutTruth]:
    """n DUTs with the population spread of martinez2022 Table 6 and sensors2023 Table 6.

    TDB spreads over -1.2..1.4 mg/C, TDSF over 0..-500 ppm/C (about one axis in seven exactly 0,
    as the clamped values in Table 6, a few near 0). Bias, scale, misalignment and
    non-orthogonality give an uncalibrated 24-position |a| - 1 g RMSE of the order of 45 mg.
    """
    if sensor not in SENSORS:
        raise StationError(f"unknown sensor {sensor!r} (known: {', '.join(SENSORS)})")
    names = check_effects(effects)
    if n < 0:
        raise StationError("number of DUTs must be >= 0")
    spec = SENSORS[sensor]
    out = []
    for i in range(n):
        rng = np.random.default_rng([int(seed), i, 0x5EED])
        bias = rng.normal(0.0, spec.bias_sigma_g, 3).clip(-2 * spec.bias_sigma_g, 2 * spec.bias_sigma_g)
        scale = 1.0 + rng.choice([-1.0, 1.0], 3) * rng.uniform(0.015, 0.04, 3)
        mis = rng.normal(0.0, 0.6, 3).clip(-1.2, 1.2)
        nonortho = rng.normal(0.0, 0.4, 3).clip(-1.0, 1.0)
        tdb = rng.uniform(-1.2, 1.4, 3)
        tdsf = -rng.uniform(0.0, 500.0, 3) * rng.uniform(0.2, 1.0, 3)  # skewed toward small values
        zero = rng.uniform(0, 1, 3) < 0.15
        tdsf[zero] = 0.0
        tdsf = np.where(np.abs(tdsf) < 1e-12, 0.0, tdsf)  # no "-0.0" in the truth JSON
        truth = DutTruth(
            serial=f"{serial_prefix}{i + 1:04d}",
            sensor=sensor,
            bias_g=bias,
            misalignment_deg=mis,
            nonorthogonality_deg=nonortho,
            scale=scale,
            tdb_mg_per_c=tdb,
            tdsf_ppm_per_c=tdsf,
            noise_g=spec.noise_g * float(rng.uniform(0.9, 1.1)),
            temp_noise_c=spec.temp_noise_c,
            temp_resolution_c=spec.temp_resolution_c,
            ug_per_lsb=spec.ug_per_lsb,
            t_lsb_per_c=spec.t_lsb_per_c,
            t_lsb_at_25c=spec.t_lsb_at_25c,
            die_tau_s=float(rng.uniform(60.0, 120.0)),
            self_heat_c=float(rng.uniform(2.0, 4.0)),
            self_heat_tau_s=float(rng.uniform(120.0, 240.0)),
            lamp_gain=float(rng.uniform(0.95, 1.05)),
        )
        for k, name in enumerate(HIDDEN_EFFECTS):  # every effect its own stream: base params fixed
            params = _draw_effect(name, np.random.default_rng([int(seed), i, 0xEFF0 + k]))
            if name in names:
                truth.effects[name] = params
        out.append(truth)
    return out


def population_to_json(truths: list[DutTruth], **meta) -> dict:
    """The truth.json document: run metadata plus one entry per DUT."""
    return {**meta, "t_ref_c": T_REF_C, "effect_notes": {k: EFFECT_NOTES[k] for k in HIDDEN_EFFECTS}, "duts": [t.to_json() for t in truths]}


def population_from_json(doc: dict) -> list[DutTruth]:
    return [DutTruth.from_json(d) for d in doc["duts"]]


__all__ = [
    "NoiseModel",
    "NOISE_MODELS",
    "NOISE_NAMES",
    "DEFAULT_NOISE",
    "noise_model",
    "SensorSpec",
    "SENSORS",
    "HIDDEN_EFFECTS",
    "EFFECT_NOTES",
    "DutTruth",
    "draw_population",
    "check_effects",
    "population_to_json",
    "population_from_json",
    "rotation_matrix",
    "nonorthogonality_matrix",
]
