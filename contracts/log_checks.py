"""The checks a log's numbers must pass before any science: header numbers in range, finite
samples, lamp and position codes, acceleration units, samples within the sensor's range
(|a| <= 16 g on every axis, -60..150 C: a hostile or corrupted file, `ay_g = 1e308`, must stop
here, not pass through the fit), temperature (kelvin named), strictly increasing time, odr_hz
against the sample times.

Why a module of its own: the checks are shared by two readers, the design-5.1 log reader
(contracts/logfile.py: read_log, parse_log, check_log) and the import of other tools' logs
(cli/commands/log_import.py), and they are a subject of their own (units table, bands, the
error lines) apart from the file format. This module knows nothing of the file format and imports
nothing from contracts.logfile, so the reader can import it without a circle.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from contracts.types import StationError

# ---- what a log must look like before any science -------------------------------------------------
# A log is believed only after a look: the wrong units, a Kelvin temperature column, a clock that
# stands still or runs backwards, or an impossible header number each made every analysis give a
# confident wrong answer (TDB x9.8 from m/s2) or hang a replay (odr_hz 1e9). Every check below is
# one StationError line naming the problem, the row (line number in the file) where there is one,
# and for the units the option that converts them.

G0_M_S2 = 9.80665
ODR_MAX_HZ = 100_000.0
TEMP_RANGE_C = (-60.0, 150.0)
# |a| on any axis above this is no acceleration a supported sensor can report (the largest full
# scale: LIS3DSH +-16 g; ADXL355 +-8 g): a corrupted row (ay_g = 1e308 moved a TDSF by 9 ppm/C)
ACC_RANGE_G = 16.0
KELVIN_MEDIAN = (213.0, 433.0)  # a median temperature there, in a column meant for C, is kelvin
# Median |a| over the samples: a DUT at rest reads 1 g in any orientation, heating changes it by
# far less than 1 %. The g band is wide on purpose (synthetic and partial logs, a few rows); the
# other units are decades away: m/s2 ~9.8, mg ~1000, raw counts hundreds to hundreds of thousands.
G_BAND = (0.2, 4.0)
UNIT_BANDS = (("m/s2", 6.0, 16.0), ("mg", 800.0, 1250.0))
COUNTS_MIN = 50.0
G_DIVISOR = {"g": 1.0, "mg": 1000.0, "m/s2": G0_M_S2}  # a value in these units / divisor = g


def g_divisor(units: str, counts_per_g: float | None = None) -> float:
    """What a value in `units` is divided by to give g (counts: the sensor's LSB per g)."""
    if units == "counts":
        if counts_per_g is None:  # what float(None) raised before: a caller's mistake, not a log's
            raise TypeError("g_divisor: units 'counts' need counts_per_g (the sensor's LSB per g)")
        return float(counts_per_g)
    return G_DIVISOR[units]
ODR_MATCH = (0.5, 2.0)  # header odr_hz x median sample interval
# Numeric header keys the station writes or reads: (test, rule shown in the error, integer?)
META_NUMBERS: dict[str, tuple[Callable[[float], bool], str, bool]] = {
    "odr_hz": (lambda v: 0.0 < v <= ODR_MAX_HZ, f"0 < odr_hz <= {ODR_MAX_HZ:.0f} Hz", False),
    "ug_per_lsb": (lambda v: 0.0 < v <= 1e5, "0 < ug_per_lsb <= 100000", False),
    "t_power_on_s": (lambda v: abs(v) <= 1e9, "-1e9 <= t_power_on_s <= 1e9 s", False),
    "lost_samples": (lambda v: 0 <= v <= 2**53, "an integer >= 0", True),
}


def _num(v: float) -> str:
    return repr(float(v))


def _show(raw: str, limit: int = 40) -> str:
    raw = raw.strip()
    return raw if len(raw) <= limit else raw[:limit] + "..."


def check_meta(meta: dict[str, str], source: str = "<log>") -> None:
    """The numeric `# key: value` header lines (META_NUMBERS) must be finite numbers in range."""
    for key, (ok, rule, integer) in META_NUMBERS.items():
        raw = meta.get(key)
        if raw is None or not raw.strip():
            continue
        head = f"{source}: header '# {key}: {_show(raw)}'"
        try:
            v = float(raw)
        except ValueError:
            raise StationError(f"{head} is not a number ({rule})") from None
        if not math.isfinite(v):
            raise StationError(f"{head} is not a finite number ({rule})")
        if (integer and v != math.floor(v)) or not ok(v):
            raise StationError(f"{head} is out of range ({rule})")


def _fmt_median(m: float) -> str:
    return f"{m:.0f}" if m >= 100 else f"{m:.3g}"


def guess_accel_units(median_norm: float) -> str | None:
    """The unit a column of static accelerations is most likely in, from its median |a|."""
    if G_BAND[0] <= median_norm <= G_BAND[1]:
        return "g"
    for unit, lo, hi in UNIT_BANDS:
        if lo <= median_norm <= hi:
            return unit
    if median_norm >= COUNTS_MIN:
        return "counts"
    return None


def accel_units_problem(median_norm: float, names: str, given: str = "g",
                        counts_per_g: float | None = None) -> str | None:
    """None when the acceleration columns read about 1 g once converted from `given`; else the
    one-line problem, naming the likely unit and the option that converts it. median_norm is the
    median |a| of the values as written in the file."""
    in_g = median_norm * (1.0 / g_divisor(given, counts_per_g))
    if G_BAND[0] <= in_g <= G_BAND[1]:
        return None
    m = _fmt_median(median_norm)
    guess = guess_accel_units(median_norm)
    counts_hint = f"give --accel-units counts --counts-per-g N (N = the sensor's LSB per g, about {m} here)"
    if given == "counts" and guess == "counts":
        return (f"{names} with --counts-per-g {counts_per_g:g} give median |a| = {_fmt_median(in_g)} g, not about 1 g: "
                f"check --counts-per-g (these read about {m} per g)")
    if guess == "g":
        return f"{names} look like g, not {given} (median |a| = {m}): drop --accel-units {given}"
    if guess in ("m/s2", "mg"):
        return f"{names} look like {guess}, not {given} (median |a| = {m}): give --accel-units {guess}"
    if guess == "counts":
        return f"{names} look like raw counts, not {given} (median |a| = {m}): {counts_hint}"
    return f"{names} do not look like {given} (median |a| = {m}; a DUT at rest reads about 1 g): check the log's units"


class LogChecker:
    """The checks of a log's samples, fed chunk by chunk (a file) or at once (a DutLog), and,
    when `store`, the columns collected into arrays that grow in place (no copy of the text, no
    list of rows): memory stays about the final arrays'.

    Row checks raise at once (non-finite samples, lamp, position); the whole-log checks (units,
    temperature, time order, odr_hz against the sample times) run in `finish`."""

    def __init__(self, source: str, names: dict[str, str] | None = None, capacity: int = 0, store: bool = True,
                 lamp: bool = False, position: bool = False, ref: bool = False, accel_units: str = "g",
                 counts_per_g: float | None = None) -> None:
        """accel_units/counts_per_g: the units of the accelerations `add` is given (an import
        converts them after `finish`), for the sensor-range check (ACC_RANGE_G)."""
        self.source = source
        self.accel_units = accel_units
        self._acc_limit = (math.inf if accel_units == "counts" and not counts_per_g
                           else ACC_RANGE_G * g_divisor(accel_units, counts_per_g))
        self.names = {"time": "time_s", "ax": "ax_g", "ay": "ay_g", "az": "az_g", "temp": "temp_c",
                      "lamp": "lamp", "position": "position", **(names or {})}
        self.store = store
        cap = max(int(capacity), 16)
        self.n = 0
        self.norm = np.empty(cap, np.float32)  # |a| per row, for the median
        self.time = np.empty(cap) if store else None
        self.acc = np.empty((cap, 3)) if store else None
        self.temp = np.empty(cap) if store else None
        self.lamp = np.empty(cap, np.int8) if store and lamp else None
        self.position = np.empty(cap, np.int64) if store and position else None
        self.ref = np.empty((cap, 3)) if store and ref else None
        self._prev: tuple[float, str] | None = None
        self._t_min, self._t_max = math.inf, -math.inf
        self._time_error: str | None = None
        self._temp_error: tuple[int, str, float] | None = None  # (row index, where, value)
        self._acc_error: tuple[int, str, str, float] | None = None  # (row index, where, column, value)
        self._dt_medians: list[float] = []
        self.temp_for_median: np.ndarray | None = None  # check_log: the DutLog's own column

    # -- per chunk ---------------------------------------------------------------------------
    def _arrays(self) -> list[np.ndarray]:
        return [a for a in (self.norm, self.time, self.acc, self.temp, self.lamp, self.position, self.ref) if a is not None]

    def _grow(self, need: int) -> None:
        cap = self.norm.shape[0]
        if need <= cap:
            return
        new = max(need, int(cap * 1.5) + 16)
        for a in self._arrays():
            a.resize((new,) + a.shape[1:], refcheck=False)

    def add(self, time_s: np.ndarray, acc: np.ndarray, temp_c: np.ndarray, lamp: np.ndarray | None = None,
            position: np.ndarray | None = None, ref: np.ndarray | None = None, lines: np.ndarray | None = None) -> None:
        m = int(time_s.shape[0])
        if m == 0:
            return
        start = self.n

        def where(k: int) -> str:
            return f"line {int(lines[k])}" if lines is not None else f"row {start + k + 1}"

        def fail(name: str, values: np.ndarray, bad: np.ndarray, why: str) -> None:
            k = int(np.flatnonzero(bad)[0])
            raise StationError(f"{self.source}: {where(k)}: {self.names[name]} = {_num(values[k])} {why}")

        for name, values in (("time", time_s), ("ax", acc[:, 0]), ("ay", acc[:, 1]), ("az", acc[:, 2]), ("temp", temp_c)):
            bad = ~np.isfinite(values)
            if bad.any():
                fail(name, values, bad, "is not a finite number")
        # beyond the sensor's range (first offence kept; reported after the units: raw counts or
        # mg exceed it in every row, and their error names the option that converts them)
        if self._acc_error is None:
            bad_rows = np.flatnonzero(np.any(np.abs(acc) > self._acc_limit, axis=1))
            if bad_rows.size:
                k = int(bad_rows[0])
                axis = int(np.flatnonzero(np.abs(acc[k]) > self._acc_limit)[0])
                self._acc_error = (start + k, where(k), ("ax", "ay", "az")[axis], float(acc[k, axis]))
        if lamp is not None:
            bad = ~np.isin(lamp, (0.0, 1.0))
            if bad.any():
                fail("lamp", lamp, bad, "must be 0 or 1")
        if position is not None:
            from contracts.positions import POSITION_NAMES

            p = position
            bad = ~(np.isfinite(p) & (p == np.round(p)) & (p >= -1) & (p < len(POSITION_NAMES)))
            if bad.any():
                fail("position", p, bad, f"must be an integer -1 (unknown) .. {len(POSITION_NAMES) - 1}")
        # time: strictly increasing (first offence kept; reported after the units and temperature)
        with np.errstate(over="ignore", invalid="ignore"):  # 1e308 - -1e308: inf, not a warning line
            self._add_times(time_s, where)
        if self._temp_error is None:
            bad = (temp_c < TEMP_RANGE_C[0]) | (temp_c > TEMP_RANGE_C[1])
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                self._temp_error = (start + k, where(k), float(temp_c[k]))
        # store
        self._grow(start + m)
        end = start + m
        with np.errstate(over="ignore", invalid="ignore"):  # a row beyond the range: |a| inf, reported in finish
            self.norm[start:end] = np.sqrt(np.einsum("ij,ij->i", acc, acc))
        if self.time is not None and self.acc is not None and self.temp is not None:  # self.store
            self.time[start:end] = time_s
            self.acc[start:end] = acc
            self.temp[start:end] = temp_c
            if self.lamp is not None:
                self.lamp[start:end] = _given(lamp, "lamp")
            if self.position is not None:
                self.position[start:end] = _given(position, "position")
            if self.ref is not None:
                self.ref[start:end] = _given(ref, "ref")
        self.n = end

    def _add_times(self, time_s: np.ndarray, where: Callable[[int], str]) -> None:
        m = int(time_s.shape[0])
        full = time_s if self._prev is None else np.concatenate(([self._prev[0]], time_s))
        d = np.diff(full)
        if self._time_error is None:
            bad = np.flatnonzero(d <= 0)
            if bad.size:
                j = int(bad[0])
                k = j if self._prev is not None else j + 1  # chunk index of the offending row
                if k > 0:
                    prev_v, prev_at = float(time_s[k - 1]), where(k - 1)
                else:  # k == 0 only after an earlier chunk: against that chunk's last row
                    assert self._prev is not None
                    prev_v, prev_at = self._prev
                tn, v = self.names["time"], float(time_s[k])
                if v == prev_v:
                    self._time_error = (f"{self.source}: {where(k)}: {tn} = {_num(v)} repeats {prev_at} "
                                        f"(a duplicated row?): sample times must increase")
                else:
                    self._time_error = (f"{self.source}: {where(k)}: {tn} = {_num(v)} goes back from {_num(prev_v)} "
                                        f"on {prev_at} (rows out of order?): sample times must increase")
        pos = d[d > 0]
        if pos.size:
            self._dt_medians.append(float(np.median(pos)))
        self._t_min = min(self._t_min, float(time_s.min()))
        self._t_max = max(self._t_max, float(time_s.max()))
        self._prev = (float(time_s[-1]), where(m - 1))

    # -- whole log -----------------------------------------------------------------------------
    def finish(self, meta: dict[str, str], accel_units: str = "g", counts_per_g: float | None = None,
               temp_units: str = "C", time_scale: float = 1.0) -> None:
        """The whole-log checks, in this order: a clock that stands still, the acceleration units,
        kelvin temperatures, the first row beyond the sensor's range (|a| > ACC_RANGE_G on an axis,
        or a temperature outside TEMP_RANGE_C), the time order, odr_hz against the sample times.
        temp_units: what the caller converted the temperatures from (they are C here)."""
        n, src, nm = self.n, self.source, self.names
        for a in self._arrays():  # trim in place (the arrays hold no copies)
            a.resize((n,) + a.shape[1:], refcheck=False)
        if n == 0:
            return
        if n >= 2 and self._t_min == self._t_max:
            raise StationError(f"{src}: {nm['time']} is {_num(self._t_min)} in every row: the log has no sample times")
        acc_names = f"{nm['ax']}/{nm['ay']}/{nm['az']}"
        problem = accel_units_problem(float(np.median(self.norm)), acc_names, accel_units, counts_per_g)
        if problem:
            raise StationError(f"{src}: {problem}")
        tn = nm["temp"]
        if self._temp_error is not None:
            temps = self.temp if self.temp is not None else self.temp_for_median
            med = float(np.median(temps)) if temps is not None else math.nan
            if temp_units.upper() == "K" and TEMP_RANGE_C[0] <= med + 273.15 <= TEMP_RANGE_C[1]:
                raise StationError(f"{src}: {tn} looks like C, not kelvin (median {med + 273.15:.2f}): drop --temp-units K")
            if temp_units.upper() != "K" and KELVIN_MEDIAN[0] <= med <= KELVIN_MEDIAN[1]:
                raise StationError(f"{src}: {tn} looks like kelvin, not C (median {med:.2f}): give --temp-units K")
        acc_row = self._acc_error[0] if self._acc_error is not None else math.inf
        temp_row = self._temp_error[0] if self._temp_error is not None else math.inf
        # the first row beyond the sensor's range, whichever column
        if self._acc_error is not None and acc_row < temp_row:
            _, at, axis, v = self._acc_error
            lim = ACC_RANGE_G
            raw = "" if self.accel_units == "g" else (
                f" ({-self._acc_limit:.6g}..{self._acc_limit:.6g} {self.accel_units})")
            raise StationError(f"{src}: {at}: {nm[axis]} = {_num(v)} is outside the sensor's range "
                               f"{-lim:g}..{lim:g} g{raw}")
        if self._temp_error is not None:
            _, at, v = self._temp_error
            raise StationError(f"{src}: {at}: {tn} = {_num(v)} is outside {TEMP_RANGE_C[0]:g}..{TEMP_RANGE_C[1]:g} C")
        if self._time_error is not None:
            raise StationError(self._time_error)
        raw = (meta.get("odr_hz") or "").strip()
        if raw and self._dt_medians:
            dt = float(np.median(self._dt_medians)) * time_scale
            ratio = float(raw) * dt
            if not ODR_MATCH[0] <= ratio <= ODR_MATCH[1]:
                raise StationError(f"{src}: header '# odr_hz: {_show(raw)}' does not match the sample times "
                                   f"(median interval {dt:.6g} s, {1.0 / dt:.6g} Hz)")


def _given(values: np.ndarray | None, column: str) -> np.ndarray:
    """A column the checker stores (made with it) must be given to every `add`."""
    if values is None:
        raise TypeError(f"LogChecker.add: no {column} column, but the checker stores one")
    return values


__all__ = ["LogChecker", "accel_units_problem", "check_meta", "g_divisor", "guess_accel_units", "G0_M_S2",
           "G_DIVISOR", "ACC_RANGE_G", "TEMP_RANGE_C"]
