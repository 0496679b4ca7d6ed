"""Noise you can see: is the model residual at the sensor's own noise, or above it? (Allan deviation)

Pure functions, arrays in, results out:

- allan(x_mg, rate_hz): overlapping Allan deviation (allantools.oadev, the acceleration treated as
  "frequency" data) on octave-spaced averaging times tau = 2^k / rate, with allantools' own error
  (adev / sqrt(number of terms)) and an honest 1-sigma interval: chi-squared with the equivalent
  degrees of freedom of NIST SP 1065 (allantools.edf_simple; the fewest of white, flicker and
  random-walk noise, i.e. the widest interval).
  NaN samples split the series; the pieces are pooled (Allan variance weighted by number of terms,
  degrees of freedom summed), never joined.
- noise_terms(curve): the standard terms of an accelerometer's Allan deviation, from a weighted
  non-negative fit sigma^2(tau) = 3 Q^2 / tau^2 + N^2 / tau + (0.664 B)^2 + K^2 tau / 3:
  white noise (velocity random walk, slope -1/2) N in mg/sqrt(Hz) = the -1/2 line at tau = 1 s;
  bias instability B = min adev / 0.664 in mg at the minimum's tau; random walk (slope +1/2)
  K in mg*sqrt(Hz) = the +1/2 line at tau = 3 s. A term is reported only when the curve shows it:
  its slope dominates the fit over at least one octave (and for the random walk the rise is beyond
  the error bars); otherwise the result says why not.
- compare_residual_to_sensor(resid_curve, static_curve): per tau the ratio of the residual's adev
  to the static segment's, with both curves' intervals, and a statement in words. "Above" needs
  >= 20 % and > 2.5 combined standard errors on >= 2 adjacent octaves. Given the Allan curve of the
  noise the model adds itself, an excess that this noise explains is named as such, not as
  unmodelled signal.
- static_segment(d): the sensor's own noise reference in a prepared log (segmentation.DutData): the
  longest stretch in one orientation with the smoothed temperature within 0.2 C.
- temperature_input_noise(d, model, axis): the noise a model adds by following the per-sample
  temperature (1 C steps and sensor noise of a LIS3DSH-class part times ~TDB: as large as the
  accelerometer's own white noise), i.e. sensitivity x (T - its 60 s mean).
- noise_view(report, k): all of it for DUT k of a DiagnosisReport, JSON-safe.

Residual = measured - model, in mg, always. Cost: ~30 ms per DUT for 117 000 samples (oadev ~5 ms
per axis and curve; no decimation needed).
"""

from __future__ import annotations

import math

import numpy as np

from station.science.chunked import median_step_s
from station.diagnostics.allan import (  # noqa: F401  (allan, noise_terms: re-exported, the noise view's API)
    MIN_PIECE, AllanCurve, _fmt_tau, _list, _num, allan, allan_pieces, noise_terms,
)

AXES = ("x", "y", "z")

STATIC_TOL_C = 0.2  # smoothed temperature within this over the static stretch
STATIC_WANT_S = 600.0  # a static stretch this long is good enough
STATIC_MIN_S = 300.0  # shorter: no static segment
STATIC_FALLBACK_MAX_C = 1.0  # the most stable stretch is used only if its temperature varies less

ABOVE_RATIO = 1.2  # "above the sensor's noise": at least 20 % above ...
ABOVE_Z = 2.5  # ... by more than 2.5 combined standard errors (log scale) ...
ABOVE_MIN_TAUS = 2  # ... on at least two adjacent octaves (Allan's filter spans ~2 octaves)




# ---- residual against sensor --------------------------------------------------------------------------

def _adjacent_runs(flag: np.ndarray, min_len: int = ABOVE_MIN_TAUS) -> list[tuple[int, int]]:
    """(first, last) index of each run of >= min_len adjacent True values."""
    out = []
    k = 0
    while k < flag.size:
        if flag[k]:
            e = k
            while e + 1 < flag.size and flag[e + 1]:
                e += 1
            if e - k + 1 >= min_len:
                out.append((k, e))
            k = e + 1
        else:
            k += 1
    return out


def _mask(runs: list[tuple[int, int]], n: int) -> np.ndarray:
    m = np.zeros(n, bool)
    for a, b in runs:
        m[a:b + 1] = True
    return m


def _at(curve: AllanCurve, m: np.ndarray) -> np.ndarray:
    """Indices of averaging factors m in curve (-1 where absent)."""
    cm = np.rint(curve.taus_s * curve.rate_hz).astype(np.int64)
    i = np.searchsorted(cm, m)
    ok = (i < cm.size) & (cm[np.minimum(i, cm.size - 1)] == m)
    return np.where(ok, i, -1)


def _where(taus: np.ndarray, runs: list[tuple[int, int]]) -> str:
    return " and ".join(f"from {_fmt_tau(taus[a])} to {_fmt_tau(taus[b])}" if b > a else f"at {_fmt_tau(taus[a])}"
                        for a, b in runs)


def compare_residual_to_sensor(resid_curve: AllanCurve, static_curve: AllanCurve, sensor_terms: dict | None = None,
                               model_noise_curve: AllanCurve | None = None,
                               model_noise_text: str = "the model's own noise", extrapolate: bool = True) -> dict:
    """Per tau: ratio residual / static adev with the static curve's 1-sigma interval, and whether the
    residual is above the sensor's noise there: >= 20 % above and beyond 2.5 combined standard errors
    (log scale), on >= 2 adjacent octaves. The statement names the sensor's terms.

    Beyond the static segment's longest tau (extrapolate=True) the reference is an upper bound of the
    sensor's noise: its deviation at a tau_a of the segment times sqrt(tau / tau_a) (per tau, the tau_a
    giving the largest z). White (-1/2), flicker (0) and random-walk (+1/2) noise never rise faster,
    so a residual above that bound is above the sensor's noise (a sensor ramp, +1, would be drift,
    i.e. signal); below it, nothing is claimed.

    model_noise_curve (optional): the Allan curve of noise the model itself adds to its prediction
    (e.g. its noisy per-sample input through the model). Where the residual is still above the sensor
    once that variance (its upper 1-sigma bound) is subtracted, the excess is unmodelled signal;
    elsewhere it is the model's noise."""
    terms = sensor_terms if sensor_terms is not None else noise_terms(static_curve)
    same_rate = math.isclose(resid_curve.rate_hz, static_curve.rate_hz, rel_tol=1e-6)
    rm = np.rint(resid_curve.taus_s * resid_curve.rate_hz).astype(np.int64)
    common = rm[_at(static_curve, rm) >= 0] if same_rate and len(static_curve) else np.zeros(0, np.int64)
    if common.size == 0:
        return {"taus_s": [], "ratio": [], "above": [], "ranges_s": [], "at_sensor_noise": None,
                "unmodelled_signal": None, "sensor_terms": terms,
                "statement": "nothing to compare: the residual and the static segment share no averaging time"}
    beyond = rm[rm > common[-1]] if extrapolate else np.zeros(0, np.int64)
    ms = np.concatenate([common, beyond])
    n_meas = common.size
    i, j = _at(resid_curve, ms), _at(static_curve, common)
    taus = resid_curve.taus_s[i]
    r = resid_curve.adev_mg[i]
    sig_r = 0.5 * np.log(resid_curve.hi_mg[i] / resid_curve.lo_mg[i])
    s_meas = static_curve.adev_mg[j]
    sig_meas = 0.5 * np.log(static_curve.hi_mg[j] / static_curve.lo_mg[j])
    t_last = float(taus[n_meas - 1])
    # beyond: the bound from each static point a, s_a sqrt(tau / tau_a), is valid; the most telling one
    # (largest z) is used: the long-tau end of a short segment is the least certain
    tb = taus[n_meas:, None]
    bounds = s_meas[None, :] * np.sqrt(tb / taus[None, :n_meas])
    z_all = np.log(np.maximum(r[n_meas:, None], 1e-300) / bounds) / np.sqrt(sig_r[n_meas:, None] ** 2
                                                                             + sig_meas[None, :] ** 2)
    anchor = np.concatenate([np.arange(n_meas), np.argmax(z_all, axis=1) if beyond.size else np.zeros(0, int)])
    s = np.concatenate([s_meas, bounds[np.arange(beyond.size), anchor[n_meas:]]])
    sig_s = sig_meas[anchor]
    sig = np.sqrt(sig_r ** 2 + sig_s ** 2)

    def test(res: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ratio = res / np.maximum(s, 1e-300)
        z = np.log(np.maximum(ratio, 1e-300)) / sig
        return ratio, z, (ratio >= ABOVE_RATIO) & (z >= ABOVE_Z)

    ratio, z, flag = test(r)
    runs = _adjacent_runs(flag)
    above = _mask(runs, flag.size)
    mn = None
    if model_noise_curve is not None and len(model_noise_curve):
        km = _at(model_noise_curve, ms)
        mn = np.where(km >= 0, model_noise_curve.adev_mg[np.maximum(km, 0)], 0.0)
        mn_hi = np.where(km >= 0, model_noise_curve.hi_mg[np.maximum(km, 0)], 0.0)
        _, _, flag_adj = test(np.sqrt(np.maximum(r * r - mn_hi * mn_hi, 0.0)))  # conservative: its upper bound
        unmod = _mask(_adjacent_runs(flag_adj & above), flag.size)
    else:
        unmod = above.copy()
    own = above & ~unmod
    unmod_runs, own_runs = _adjacent_runs(unmod, 1), _adjacent_runs(own, 1)
    sensor = f"sensor: {terms['text']}"
    bound_txt = (f"beyond {_fmt_tau(t_last)} (the static segment is {static_curve.duration_s / 60:.0f} min) against "
                 f"its deviation extrapolated as sqrt(tau), an upper bound of white, flicker and random-walk noise")
    worst = int(np.flatnonzero(above)[np.argmax(ratio[above])]) if above.any() else int(np.argmax(ratio))
    if not runs:
        statement = (f"the residual is at the sensor's noise at all averaging times (within the error bars), "
                     f"{_fmt_tau(taus[0])} to {_fmt_tau(t_last)}")
        if beyond.size:
            statement += f", and not above it up to {_fmt_tau(taus[-1])} ({bound_txt})"
        statement += f"; {sensor}"
    else:
        head = (f"the residual is above the sensor's noise for averaging times {_where(taus, runs)} "
                f"(up to {ratio[worst]:.2g}x at {_fmt_tau(taus[worst])})")
        own_txt = ""
        if own_runs:
            k0 = own_runs[0][0]
            own_txt = f"{model_noise_text}, {mn[k0]:.2g} mg at {_fmt_tau(taus[k0])}, not unmodelled signal"
        if unmod_runs and own_runs:
            statement = (f"{head}: unmodelled signal {_where(taus, unmod_runs)}; {_where(taus, own_runs)} it is "
                         f"{own_txt}")
        elif unmod_runs:
            statement = f"{head}: unmodelled signal at those time scales"
        else:
            statement = f"{head}: {own_txt}"
        if above[n_meas:].any():
            statement += f"; {bound_txt}"
        statement += f"; {sensor}"
    uw = int(np.flatnonzero(unmod)[np.argmax(ratio[unmod])]) if unmod.any() else None
    return {
        "taus_s": _list(taus, 5), "ratio": _list(ratio, 4), "z": _list(z, 3), "above": [bool(x) for x in above],
        "unmodelled": [bool(x) for x in unmod],
        "reference": ["static"] * n_meas + ["bound"] * int(beyond.size),
        "bound_anchor_tau_s": [_num(taus[a], 5) for a in anchor[n_meas:]],
        "residual_adev_mg": _list(r), "static_adev_mg": _list(s),
        "static_lo_mg": _list(s * np.exp(-sig_s)), "static_hi_mg": _list(s * np.exp(sig_s)),
        "model_noise_adev_mg": _list(mn) if mn is not None else None,
        "ranges_s": [[_num(taus[a], 5), _num(taus[b], 5)] for a, b in runs],
        "unmodelled_ranges_s": [[_num(taus[a], 5), _num(taus[b], 5)] for a, b in unmod_runs],
        "model_noise_ranges_s": [[_num(taus[a], 5), _num(taus[b], 5)] for a, b in own_runs],
        "max_ratio": _num(ratio[worst], 4), "max_ratio_tau_s": _num(taus[worst], 5),
        "max_unmodelled_ratio": _num(ratio[uw], 4) if uw is not None else None,
        "max_unmodelled_ratio_tau_s": _num(taus[uw], 5) if uw is not None else None,
        "compared_taus_s": [_num(taus[0], 5), _num(t_last, 5)],
        "bound_taus_s": [_num(taus[n_meas], 5), _num(taus[-1], 5)] if beyond.size else None,
        "at_sensor_noise": not runs, "unmodelled_signal": bool(unmod_runs),
        "sensor_terms": terms, "statement": statement,
        "rule": (f"above = residual adev >= {ABOVE_RATIO:g} x the sensor's (static segment; beyond it, the bound "
                 f"static(tau_a) x sqrt(tau / tau_a) of the most telling tau_a) and beyond {ABOVE_Z:g} combined 1-sigma (chi-squared, log scale) "
                 f"on >= {ABOVE_MIN_TAUS} adjacent octaves; unmodelled = still above with the model's own noise "
                 f"variance (its upper 1-sigma bound) subtracted"),
    }


# ---- static segment ------------------------------------------------------------------------------------

def _block_arrays(d):
    bs = np.asarray(d.block_starts, dtype=np.int64)
    be = np.concatenate([bs[1:], [d.n]])
    ts = d.temp_smooth_c
    tmin = np.minimum.reduceat(ts, bs)
    tmax = np.maximum.reduceat(ts, bs)
    return bs, be, d.time_s[bs], d.time_s[be - 1], tmin, tmax, np.asarray(d.block_run)


def _run_ranges(run_b: np.ndarray) -> list[tuple[int, int]]:
    cut = np.flatnonzero(np.diff(run_b) != 0) + 1
    a = np.concatenate([[0], cut])
    b = np.concatenate([cut, [run_b.size]])
    return list(zip(a.tolist(), b.tolist()))


def _longest_within(t0, t1, tmin, tmax, a: int, b: int, tol: float, dt: float) -> tuple[float, int, int]:
    """Longest stretch of blocks a..b-1 whose temperature range is <= tol (two pointers, monotone deques)."""
    from collections import deque

    best = (0.0, a, a)
    lo = a
    qmax: deque = deque()
    qmin: deque = deque()
    for j in range(a, b):
        while qmax and tmax[qmax[-1]] <= tmax[j]:
            qmax.pop()
        qmax.append(j)
        while qmin and tmin[qmin[-1]] >= tmin[j]:
            qmin.pop()
        qmin.append(j)
        while qmax and tmax[qmax[0]] - tmin[qmin[0]] > tol:
            lo += 1
            if qmax[0] < lo:
                qmax.popleft()
            if qmin and qmin[0] < lo:
                qmin.popleft()
        if lo > j:  # this block alone varies by more than tol
            qmax.clear()
            qmin.clear()
            continue
        dur = t1[j] - t0[lo] + dt
        if dur > best[0]:
            best = (dur, lo, j + 1)
    return best


def static_segment(d) -> dict:
    """The sensor's own noise reference in a prepared log (DutData): the longest stretch in ONE
    orientation (constant-orientation run) with the smoothed temperature within 0.2 C. If none of
    >= 10 min, the longest of >= 5 min; if none of those, the most stable 10 min (or the whole run,
    >= 5 min) with the temperature within 1 C, said so; otherwise none. Returns
    {"found", "start_s", "end_s", "duration_s", "orientation", "temp_c", "temp_range_c", "i0", "i1",
    "criterion", "note"}; its acceleration minus its mean, per axis, is the reference."""
    n = d.n
    if n < MIN_PIECE:
        return {"found": False, "note": "no static segment in this log (too few samples)"}
    dt = median_step_s(d.time_s)
    bs, be, t0, t1, tmin, tmax, run_b = _block_arrays(d)
    runs = _run_ranges(run_b)
    best = (0.0, 0, 0)
    for a, b in runs:
        cand = _longest_within(t0, t1, tmin, tmax, a, b, STATIC_TOL_C, dt)
        if cand[0] > best[0]:
            best = cand
    criterion = f"the longest stretch in one orientation with the smoothed temperature within {STATIC_TOL_C:g} C"
    note = ""
    if best[0] < STATIC_MIN_S - 1e-9:
        # fall back: the most stable ~10 min of any run of >= 5 min
        fb = None  # (range, a, b)
        for a, b in runs:
            dur_run = t1[b - 1] - t0[a] + dt
            if dur_run < STATIC_MIN_S - 1e-9:
                continue
            want = min(STATIC_WANT_S, dur_run)
            for i in range(a, b):
                j = int(np.searchsorted(t1[a:b], t0[i] + want - dt - 1e-9)) + a
                if j >= b:
                    break
                rng = float(tmax[i:j + 1].max() - tmin[i:j + 1].min())
                if fb is None or rng < fb[0]:
                    fb = (rng, i, j + 1)
        if fb is None or fb[0] > STATIC_FALLBACK_MAX_C:
            why = ("no stretch of >= 5 min in one orientation" if fb is None else
                   f"the steadiest 5-10 min in one orientation varies by {fb[0]:.2g} C")
            return {"found": False,
                    "note": f"no static segment in this log ({why}): nothing to compare the residual against"}
        best = (t1[fb[2] - 1] - t0[fb[1]] + dt, fb[1], fb[2])
        criterion = "the most stable stretch in one orientation (fallback)"
        note = (f"no stretch of >= {STATIC_MIN_S / 60:g} min within {STATIC_TOL_C:g} C: using the most stable "
                f"{best[0] / 60:.0f} min (temperature range {fb[0]:.2g} C; thermal drift may lift its long taus: conservative)")
    elif best[0] < STATIC_WANT_S - 1e-9:
        note = (f"no stretch of >= {STATIC_WANT_S / 60:g} min within {STATIC_TOL_C:g} C: the longest is "
                f"{best[0] / 60:.1f} min (averaging times only up to a quarter of it)")
    i0, i1 = int(bs[best[1]]), int(be[best[2] - 1])
    temp = d.temp_smooth_c[i0:i1]
    return {"found": True, "start_s": _num(d.time_s[i0], 7), "end_s": _num(d.time_s[i1 - 1], 7),
            "duration_s": _num(best[0], 5), "orientation": str(d.pos_labels[int(d.pos[i0])]),
            "temp_c": _num(float(np.mean(temp)), 4), "temp_range_c": _num(float(np.ptp(temp)), 3),
            "i0": i0, "i1": i1, "criterion": criterion, "note": note}


# ---- one DUT of a diagnosis ------------------------------------------------------------------------------

def _finite_ranges(d, x: np.ndarray) -> list[tuple[int, int]]:
    """(a, b) sample ranges of x (n,) that are NaN-free and inside one constant-orientation run."""
    run_b = np.asarray(d.block_run)  # a run changes only where a block starts
    cut = np.asarray(d.block_starts)[np.flatnonzero(np.diff(run_b) != 0) + 1]
    out = []
    for a, b in zip(np.concatenate([[0], cut]), np.concatenate([cut, [d.n]])):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], np.isfinite(x[a:b]).astype(np.int8), [0]])))
        out += [(a + p, a + q) for p, q in zip(edges[::2], edges[1::2]) if q - p >= MIN_PIECE]
    return out


def residual_pieces(d, resid: np.ndarray, axis: int) -> list[np.ndarray]:
    """The residual of one axis cut into constant-orientation runs and NaN-free pieces."""
    return [resid[a:b, axis] for a, b in _finite_ranges(d, resid[:, axis])]


def temperature_input_noise(d, model_mg: np.ndarray, axis: int, window_s: float = 60.0) -> tuple[list[np.ndarray], float]:
    """The noise a model adds by following the per-sample temperature (its sensor noise and quantization
    steps): c (T - T_smooth), T_smooth the zero-phase 60 s mean (effects.smooth_temperature), with the
    model's sensitivity c (mg/C) regressed per run on the model's own high-pass (model - its 60 s mean).
    Returns the pieces (as residual_pieces) and the overall c."""
    from station.diagnostics.effects import smooth_temperature

    pieces, num, den = [], 0.0, 0.0
    ts = d.temp_smooth_c
    for a, b in _finite_ranges(d, model_mg[:, axis]):
        m = model_mg[a:b, axis]
        hp = m - smooth_temperature(m, d.time_s[a:b], window_s)
        e = d.temp_c[a:b] - ts[a:b]
        ee = float(e @ e)
        c = float(hp @ e) / ee if ee > 0 else 0.0
        num += float(hp @ e)
        den += ee
        pieces.append(c * e)
    return pieces, (num / den if den > 0 else 0.0)


def _position_name(label: str) -> str:
    try:
        from contracts.positions import POSITION_NAMES

        k = int(label)
        return f"position {label} ({POSITION_NAMES[k]})" if 0 <= k < len(POSITION_NAMES) else f"position {label}"
    except (ValueError, ImportError):
        return f"orientation {label}"


def noise_view(report, k: int = 0) -> dict:
    """Allan deviation of DUT k's residual (report.model.resid[k], measured - model, mg; pooled over its
    constant-orientation runs) against the sensor's static segment, per axis, with the sensor's noise
    terms, the model's own input noise and statements in words; JSON-safe."""
    d = report.data[k]
    rate = 1.0 / median_step_s(d.time_s)
    seg = static_segment(d)
    axes = {}
    for i, ax in enumerate(AXES):  # one axis at a time: its residual and model, not the (n, 3) ones
        resid_i = np.asarray(report.model.resid_axis(k, i), dtype=np.float64)[:, None]
        rc = allan_pieces(residual_pieces(d, resid_i, 0), rate)
        model_i = (d.acc_mg[:, i] - resid_i[:, 0])[:, None]
        del resid_i
        mpieces, coef = temperature_input_noise(d, model_i, 0)
        mc = allan_pieces(mpieces, rate)
        entry: dict = {"residual": rc.to_json(), "residual_terms": noise_terms(rc), "model_noise": mc.to_json(),
                       "model_temperature_coef_mg_per_c": _num(coef)}
        if seg["found"]:
            x = d.acc_mg[seg["i0"]:seg["i1"], i]
            sc = allan(x - np.nanmean(x), rate)
            terms = noise_terms(sc)
            cmp = compare_residual_to_sensor(
                rc, sc, terms, model_noise_curve=mc,
                model_noise_text=(f"the model's own noise (it follows the per-sample temperature's noise and "
                                  f"steps at {abs(coef):.2g} mg/C)"))
            entry.update({"static": sc.to_json(), "terms": terms, "comparison": cmp, "statement": cmp["statement"]})
        else:
            entry.update({"static": None, "terms": None, "comparison": None,
                          "statement": f"no static segment: the residual alone: {entry['residual_terms']['text']}"})
        axes[ax] = entry
    seg_json = {kk: v for kk, v in seg.items() if kk not in ("i0", "i1")}
    if seg["found"]:
        seg_json["where"] = _position_name(seg["orientation"])
    return {"serial": d.serial, "residual": "measured - model, mg", "static_segment": seg_json, "axes": axes,
            "method": ("overlapping Allan deviation (allantools.oadev) on octave taus up to a quarter of each piece; "
                       "the residual pooled over constant-orientation runs (Allan variance weighted by its number of "
                       "terms, no joins); the static segment minus its mean; 1-sigma chi-squared intervals (NIST SP "
                       "1065 edf); the model's own noise = its sensitivity to the per-sample temperature times the "
                       "temperature minus its 60 s mean"),
            "statement": _summary(d.serial, seg_json, axes, _leftover_of(report, d.serial))}


def _leftover_of(report, serial: str) -> dict | None:
    """The report's leftover for this DUT (leftover.py), if a residual remains above what the noise
    model expects on the held-out legs."""
    lo = getattr(report, "leftover", None) or {}
    if not lo.get("above_floor") or list(lo.get("model") or []) != list(report.model.effects):
        return None
    per = (lo.get("per_dut") or {}).get(serial) or {}
    above = [ax for ax, v in per.items() if v.get("above")]
    return {"axes": above, "ratio": lo.get("ratio")} if above else None


def _summary(serial: str, seg: dict, axes: dict, left: dict | None = None) -> str:
    if not seg["found"]:
        return f"{serial}: {seg['note']}."
    where = (f"static segment {float(seg['duration_s']) / 60:.0f} min in {seg['where']} at "
             f"{float(seg['temp_c']):.1f} C")
    cmp = {ax: e["comparison"] for ax, e in axes.items()}
    at = [ax for ax, c in cmp.items() if c["at_sensor_noise"]]
    unmod = [ax for ax, c in cmp.items() if c["unmodelled_signal"]]
    own = [ax for ax, c in cmp.items() if c["at_sensor_noise"] is False and not c["unmodelled_signal"]]
    none = [ax for ax, c in cmp.items() if c["at_sensor_noise"] is None]
    parts = []
    if unmod:
        per = []
        for n_, ax in enumerate(unmod):
            c = cmp[ax]
            rng = " and ".join(f"from {_fmt_tau(a)} to {_fmt_tau(b)}" for a, b in c["unmodelled_ranges_s"])
            ratio = f"{c['max_unmodelled_ratio']:.2g}x" + (" the sensor's noise" if n_ == 0 else "")
            per.append(f"on {ax} {rng} (up to {ratio} at {_fmt_tau(c['max_unmodelled_ratio_tau_s'])})")
        parts.append("the residual holds unmodelled signal " + ", ".join(per))
    if own:
        lo = min(cmp[ax]["model_noise_ranges_s"][0][0] for ax in own)
        hi = max(cmp[ax]["model_noise_ranges_s"][-1][1] for ax in own)
        parts.append(f"the residual is above the sensor's noise on {', '.join(own)} from {_fmt_tau(lo)} to "
                     f"{_fmt_tau(hi)} only by the model's own noise (it follows the per-sample temperature's noise "
                     f"and steps)")
    if at:
        lo = min(cmp[ax]["compared_taus_s"][0] for ax in at)
        hi = max(cmp[ax]["compared_taus_s"][1] for ax in at)
        bound = [cmp[ax]["bound_taus_s"][1] for ax in at if cmp[ax].get("bound_taus_s")]
        span = (f"({_fmt_tau(lo)} to {_fmt_tau(hi)}, within the error bars"
                + (f"; not above its upper bound up to {_fmt_tau(max(bound))}" if bound else "") + ")")
        left_at = [ax for ax in at if left and ax in left["axes"]]
        if left_at:
            # the Allan curve reaches a fraction of one dwell; the held-out legs reach the whole log
            parts.append(f"the residual's noise matches the sensor's on {', '.join(left_at)} only at the averaging "
                         f"times an Allan curve of one dwell reaches {span}: over whole held-out legs it is "
                         f"{left['ratio']}x what the noise model expects, an unexplained residual remains")
        rest = [ax for ax in at if ax not in left_at]
        if rest:
            parts.append(f"the residual is at the sensor's noise on {', '.join(rest)} at all averaging times compared "
                         + span)
    if none:
        parts.append(f"{', '.join(none)} not compared")
    return f"{serial}: " + "; ".join(parts) + f" ({where})."


# ---- JSON helpers ----------------------------------------------------------------------------------------

__all__ = ["AllanCurve", "allan", "allan_pieces", "noise_terms", "compare_residual_to_sensor", "static_segment",
           "residual_pieces", "temperature_input_noise", "noise_view"]
