"""Offline thermal fit: regression over all stable data (the "Regr." column of martinez2022 Table 5).

Where the streaming calibrator keeps two 1000-sample averages per orientation, the offline fit
uses every sample the calibrator's gradient gate calls stable, so it sees more temperatures and
more samples (and any number of temperature steps). Per orientation (the calibrator's own
orientation counter, the same rule): acceleration = Acc0_i + TD_i (T - 25) by least squares per
axis; then TDSF/TDB from the (TD_i, Acc0_i) points: eqs. 8/9 for two orientations, a weighted
straight line for more (the paper's six-test reference, Fig. 12).

Details:
- Samples taken while the plate moves (the few samples between a turn's start and the moment the
  filtered acceleration registers it) are still "thermally stable"; they are dropped by a
  stillness test, |raw - filtered acceleration| under `still_sigma` robust noise sigmas per axis.
- The temperature reading is noisy and quantized (LIS3DSH: 1 C steps), which biases an ordinary
  least-squares slope toward zero by var(noise)/var(T) (errors in variables). The reading noise
  variance is estimated from first differences within stable runs (var(diff)/2) and removed from
  the temperature variance (a method-of-moments correction; ~0.1 % on a 25 C step).
- The wander term's level is the part's own (station/science/part_noise.py): the class's structure
  function scaled to the part's measured white noise; the class constant only where the still data
  are too short to tell.
- Uncertainty: samples are autocorrelated (slow drifts, filtering, unmodelled effects), so the
  per-sample OLS standard error would be far too small. The 1-sigma of each TD_i comes from batch
  means: the stable runs are cut into blocks of `block_samples` consecutive samples, the block means
  are regressed (weighted by block size) and the scatter of the block means (about a parabola
  when there are five or more: TD_i is the chord of the part's response over its data, so a curved
  part's bow is not noise of it) gives the slope variance. Correlation shorter than a block is
  thus absorbed. It is propagated to
  TDB/TDSF through the weighted line fit (scaled by the reduced chi-square when > 1 with more than
  two orientations). Acc0_i errors are neglected (micro-g against a >1 g lever).
- What batch means cannot see (docs/verdicts.md "Uncertainty budget"): the ambient and hot data of
  one orientation are tens of minutes apart, so a bias that wanders (random walk, flicker) between
  them moves the slope exactly like a temperature coefficient, and the scatter about the line does
  not show it. Three more terms enter each TD_i's variance, each the variance of the same linear
  combination of block means that the slope is (weights a_b = n_b (T_b - mean T) / Sxx):
    wander     -1/2 sum_ij a_i a_j D(|t_i - t_j|), D the bias structure function of the sensor
               class (BiasWander: random walk + decade-spaced Gauss-Markov flicker, measured on a
               long static log with `characterise_bias_wander`);
    quantiser  TD^2 sum_k A_k^2/2 |sum_b a_b <exp(2 pi i k T/q)>_b|^2: the mean reading of a steady
               temperature is off by a periodic function of where T sits between the q-wide steps
               (LIS3DSH: 1 C), amplitude A_k = q/(pi k) exp(-2 pi^2 k^2 s^2/q^2) for a reading dithered
               by noise s; it does not average down while T is steady, only when T moves across steps;
    lag        (TD tau_lag sum_b a_b dT/dt_b)^2: the MEMS behind the temperature sensor by up to
               tau_lag, so a segment logged while T still creeps reads the wrong temperature.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from station.science.bias_wander import (LAG_SIGMA_S, NO_WANDER, WANDER_BY_SENSOR, BiasWander,  # noqa: F401 (re-exported)
                                         characterise_bias_wander,
                                         wander_for)
from station.science.chunked import (PIECE, diffs, median_into, median_step_s, pairwise_sum, pieces, rows_sum,
                                     split_bounds, values)
from station.science.drift_coefficients import InsufficientData, build_result
from station.science.gate_trace import GateTrace, trace_gate
from station.science.part_noise import PartNoise, measure_part_noise
from station.science.streaming_config import StreamingConfig
from contracts.types import ThermalResult


ONE_PASS_SAMPLES = 1 << 18  # an orientation's regression in one piece up to this (~20 MB of temporaries)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous [start, end) runs where mask is True."""
    if not mask.any():
        return []
    d = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist()))


def robust_sigma_g(acc_g: np.ndarray, trace: GateTrace, mask: np.ndarray) -> np.ndarray:
    """(3,) 1.4826 x the median absolute deviation of raw - filtered acceleration over the masked
    samples, per axis: one axis at a time in one buffer of the masked count (the same medians as of
    the (n, 3) residual, without it)."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    out = np.empty(3)
    buf = np.empty(int(np.count_nonzero(mask)))
    for k in range(3):
        w = 0
        for a, b in trace.spans():
            r = (acc[a:b, k] - trace.acc_filt_between(a, b)[:, k])[mask[a:b]]
            buf[w:w + r.shape[0]] = r
            w += r.shape[0]
        buf -= median_into(buf)
        np.abs(buf, out=buf)
        out[k] = 1.4826 * median_into(buf)
    return out


def usable_mask(acc_g: np.ndarray, trace: GateTrace, still_sigma: float = 8.0, floor_g: float = 2e-4) -> np.ndarray:
    """Thermally stable (gate open) and mechanically still samples."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    stable = trace.stable
    if np.count_nonzero(stable) >= 10:
        sigma = robust_sigma_g(acc, trace, stable)
    else:
        sigma = np.zeros(3)
    tol = np.maximum(still_sigma * sigma, floor_g)
    use = np.empty(stable.shape[0], dtype=bool)
    for a, b in trace.spans():  # still: |raw - filtered| under tol on every axis
        use[a:b] = stable[a:b] & np.all(np.abs(acc[a:b] - trace.acc_filt_between(a, b)) < tol, axis=1)
    return use


def white_density_ug_per_sqrt_hz(time_s, acc_g, trace: GateTrace, use: np.ndarray, alpha: float) -> float:
    """White noise density (mean over axes) of the usable samples: robust sigma of raw - filtered,
    corrected for the filter (var(e) = var_w 2 (1 - a)/(2 - a)), over sqrt(ODR / 2)."""
    t = np.asarray(time_s, dtype=np.float64)
    if np.count_nonzero(use) < 50 or t.size < 2:
        return float("nan")
    dt = median_step_s(t)
    if not dt > 0:
        return float("nan")
    sg = robust_sigma_g(acc_g, trace, use)
    sg = sg / math.sqrt(2.0 * (1.0 - alpha) / (2.0 - alpha))
    return float(np.mean(sg)) / math.sqrt(0.5 / dt) * 1e6


def temperature_quantum_c(temp_c) -> float:
    """Step of the temperature reading (LIS3DSH 1 C, ADXL355 ~0.11 C); 0 for a continuous reading."""
    return _quantum_of_levels(np.unique(np.asarray(temp_c, dtype=np.float64)), np.asarray(temp_c).size)


def _quantum_of_levels(lv: np.ndarray, n: int) -> float:
    """temperature_quantum_c from the distinct readings lv (sorted) of n samples."""
    if lv.size < 2:
        return 0.0
    d = np.diff(lv)
    d = d[d > 1e-9]
    q = float(d.min()) if d.size else 0.0
    if q < 1e-3 or lv.size > 0.25 * n:
        return 0.0
    return q


def temperature_dither_c(temp_c, runs, quantum_c: float) -> float:
    """Reading noise before quantisation: var(first differences)/2 = s^2 + q^2/12 within runs."""
    temp = np.asarray(temp_c, dtype=np.float64)
    d = diffs(temp, runs)  # the runs' differences, a piece at a time
    if d.n < 10:
        return 0.0
    return math.sqrt(max(0.5 * (pairwise_sum(lambda a, b: d.piece(a, b) ** 2, d.n) / d.n) - quantum_c ** 2 / 12.0, 0.0))


def quantiser_amplitudes_c(quantum_c: float, dither_c: float, n_harm: int = 5) -> np.ndarray:
    """A_k (C) of the periodic error of a dithered quantiser's mean reading (Fourier series of the
    rounding error convolved with the Gaussian dither); sum A_k^2/2 = q^2/12 without dither."""
    if quantum_c <= 0:
        return np.zeros(0)
    k = np.arange(1, n_harm + 1)
    return quantum_c / (math.pi * k) * np.exp(-2.0 * math.pi ** 2 * k * k * dither_c ** 2 / quantum_c ** 2)


def block_features(time_s, temp_filt_c: np.ndarray | Callable[[int, int], np.ndarray], quantum_c: float,
                   blocks: Sequence[tuple[int, int]], n_harm: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block [start, end) of samples: mean time (s), temperature rate (C/s, of the filtered
    reading) and the mean phasor exp(2 pi i k T/q) of the filtered temperature for k = 1..n_harm
    (quantiser phase). temp_filt_c: the filtered temperature, an array or a function (a, b) ->
    its samples [a, b) (GateTrace.temp_filt_between: the trace keeps no copy of it).

    Chunked (issue 40): the blocks are taken in groups of consecutive blocks spanning at most
    PIECE samples; the group's filtered temperature and its phasors (n_harm complex values a
    sample) exist for that group only, and each block's figures are those of its own samples,
    with the same operations as one block at a time (tests/test_long_logs.py)."""
    t = np.asarray(time_s, dtype=np.float64)
    temp_of: Callable[[int, int], np.ndarray]
    if callable(temp_filt_c):
        temp_of = temp_filt_c
    else:
        tf_all = np.asarray(temp_filt_c, dtype=np.float64)
        temp_of = lambda a, b: tf_all[a:b]  # noqa: E731
    k = np.arange(1, n_harm + 1)
    nb = len(blocks)
    bt, bg = np.empty(nb), np.empty(nb)
    ph = np.zeros((nb, n_harm), dtype=complex)
    i = 0
    while i < nb:
        j, lo = i + 1, blocks[i][0]  # a group: consecutive blocks, in order, within PIECE samples
        while j < nb and blocks[j][0] >= blocks[j - 1][1] and blocks[j][1] - lo <= PIECE:
            j += 1
        hi = blocks[j - 1][1]
        tf = temp_of(lo, hi)
        if quantum_c > 0:
            phase = np.exp(2j * np.pi * np.outer(tf, k) / quantum_c)
        for m in range(i, j):
            a, b = blocks[m]
            tb = t[a:b]
            bt[m] = tb.mean()
            bg[m] = float(np.polyfit(tb - tb.mean(), tf[a - lo:b - lo], 1)[0]) if b - a >= 3 and np.ptp(tb) > 0 else 0.0
            if quantum_c > 0:
                ph[m] = phase[a - lo:b - lo].mean(axis=0)
        i = j
    return bt, bg, ph


def _levels(temp: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """np.unique(temp[mask]), a chunk at a time (the union of each chunk's distinct values)."""
    parts = [np.unique(temp[a:b][mask[a:b]]) for a, b in pieces([(0, temp.shape[0])])]
    return np.unique(np.concatenate(parts)) if parts else np.empty(0)


def budget_inputs(time_s, acc_g, temp_c, trace: GateTrace, use: np.ndarray, alpha: float,
                  sensor: str | None = None, wander: BiasWander | str | None = None
                  ) -> tuple[float, float, np.ndarray, BiasWander]:
    """What every budget of one record shares (the offline slope and the residual's curvature
    alike): (temperature quantum C, its dither C, the quantiser amplitudes A_k C, the bias-wander
    class). wander None: white noise only; a string ("auto", "class"): `wander_for(sensor, white
    noise)`, the class whose level `offline_fit` then measures on the part ("auto") or keeps."""
    temp = np.asarray(temp_c, dtype=np.float64)
    runs = [(s, e) for s, e in _runs(use) if e - s >= 2]
    quantum = _quantum_of_levels(_levels(temp, use), int(np.count_nonzero(use))) if use.any() else 0.0
    dither = temperature_dither_c(temp, runs, quantum)
    if wander is None:
        wander = NO_WANDER
    elif isinstance(wander, str):
        wander = wander_for(sensor, white_density_ug_per_sqrt_hz(time_s, acc_g, trace, use, alpha))
    return quantum, dither, quantiser_amplitudes_c(quantum, dither), wander


def combination_budget(weights, block_time_s, block_rate_c_per_s, block_phasor, sensitivity_g_per_c,
                       wander: BiasWander, amplitudes_c: np.ndarray, lag_sigma_s: float) -> dict[str, np.ndarray]:
    """Variances (g^2, per axis) that a linear combination sum_b w_b y_b of block means (a slope or
    a curvature) gets from bias wander, temperature quantisation and MEMS lag. sensitivity_g_per_c
    (3,): dy/dT of the signal (TD_i for the raw data, for compensated data the TDB the board
    subtracts with the reading) that turns a temperature error into an acceleration error."""
    w = np.asarray(weights, dtype=np.float64)
    sens = np.abs(np.asarray(sensitivity_g_per_c, dtype=np.float64)).reshape(-1)
    wand = wander.combination_var_g2(w, block_time_s)
    q = 0.0
    if amplitudes_c.size:
        s = np.abs(w @ block_phasor[:, : amplitudes_c.size]) ** 2
        q = float(np.sum(amplitudes_c ** 2 / 2.0 * s))
    lag = (lag_sigma_s * float(w @ block_rate_c_per_s)) ** 2
    return {"wander": np.full(sens.shape, wand), "quantiser": sens ** 2 * q, "lag": sens ** 2 * lag}


def offline_fit(
    time_s,
    acc_g,
    temp_c,
    config: StreamingConfig | None = None,
    *,
    block_samples: int = 200,
    still_sigma: float = 8.0,
    min_span_c: float | None = None,
    eiv_correction: bool = True,
    trace: GateTrace | None = None,
    sensor: str | None = None,
    wander: BiasWander | str | None = None,
    lag_sigma_s: float = LAG_SIGMA_S,
) -> ThermalResult:
    """TDB/TDSF per axis (method "offline") with 1-sigma uncertainties.

    min_span_c: an orientation is used when its stable data spans at least this temperature range
    (default config.segment_delta_c / 2). trace: a precomputed `trace_gate` result (saves a pass).
    wander: the bias wander of the part (None: white noise only, as a synthetic record; "auto": the
    class `wander_for(sensor, measured white noise)` at the level measured on the part's own still
    runs, station/science/part_noise.py, what `calibrate` uses; "class": the class constant as it is;
    a BiasWander: that one);
    lag_sigma_s: standard uncertainty of the MEMS-behind-sensor lag. The result carries
    `.uncertainty`: per orientation and axis the TD_i variance of each budget term (mg/C)^2, the
    TDB/TDSF correlation, and the quantiser/wander inputs used (module doc).
    """
    cfg = config or StreamingConfig()
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    if trace is None:
        trace, _ = trace_gate(t, acc, temp, cfg)
    use = usable_mask(acc, trace, still_sigma)
    quantum, dither, amps, cls = budget_inputs(t, acc, temp, trace, use, cfg.alpha_acc, sensor, wander)
    budget: dict[int, dict[str, np.ndarray]] = {}
    span_needed = cfg.pair_delta_c() if min_span_c is None else float(min_span_c)
    drifts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    sigmas: dict[int, np.ndarray] = {}
    pending: dict[int, tuple] = {}  # orientation -> what its budget needs once the wander is known
    still_runs: list[tuple[int, int]] = []
    chord_x: dict[int, float] = {}
    n_runs = 0
    by_orientation = runs_by_orientation(use, trace.orientation)
    for o in np.unique(trace.orientation):
        runs = [(s, e) for s, e in by_orientation.get(int(o), []) if e - s >= 2]
        n = sum(e - s for s, e in runs)
        if n < max(cfg.average_samples, 10):
            continue
        # block means (batch means) over the stable runs of this orientation
        bx, by, bn, blocks = [], [], [], []
        for s, e in runs:
            nb = max(1, int(round((e - s) / block_samples)))
            for a, b in split_bounds(s, e, nb):
                bx.append(temp[a:b].mean())
                by.append(acc[a:b].mean(axis=0))
                bn.append(b - a)
                blocks.append((a, b))
        bx, by, bn = np.array(bx), np.array(by), np.array(bn, dtype=np.float64)
        if np.ptp(bx) < span_needed:
            continue
        if np.any(np.ptp(by, axis=0) > cfg.orientation_delta_g):
            raise InsufficientData(
                f"offline: orientation {int(o)} holds data more than {cfg.orientation_delta_g:g} g apart; "
                "the plate was turned before a segment could be logged"
            )
        n_runs += len(runs)
        td, acc0, chord_x[int(o)] = _regression(temp, acc, runs, cfg.t_ref_c, eiv_correction)
        still_runs.extend(runs)
        # batch-means slope uncertainty
        m = bx.shape[0]
        if m >= 3:
            bxm = np.average(bx - cfg.t_ref_c, weights=bn)
            bxc = bx - cfg.t_ref_c - bxm
            sbxx = float(np.sum(bn * bxc * bxc))
            bym = np.average(by, axis=0, weights=bn)
            if m >= 5:  # the scatter about a parabola: a curved part's bow is no noise of its chord
                X = np.column_stack([np.ones(m), bxc, bxc * bxc])
                XtW = X.T * bn
                res_b = by - X @ (np.linalg.pinv(XtW @ X) @ XtW @ by)
                s2 = np.sum(bn[:, None] * res_b * res_b, axis=0) / (m - 3)
            else:
                bslope = (bn * bxc) @ (by - bym) / sbxx
                res_b = by - bym - np.outer(bxc, bslope)
                s2 = np.sum(bn[:, None] * res_b * res_b, axis=0) / (m - 2)
            w_slope = bn * (bx - cfg.t_ref_c - np.average(bx - cfg.t_ref_c, weights=bn)) / sbxx
            pending[int(o)] = (s2 / sbxx, w_slope, blocks, td)
        else:
            sigmas[int(o)] = np.full(3, np.inf)
        drifts[int(o)] = (td, acc0)
    noise = part_noise_of(t, acc, sorted(still_runs), cls, wander)
    for o, (var_fit, w_slope, blocks, td) in pending.items():
        # what batch means cannot see: the slope's own weights on the block means
        bt, bg, ph = block_features(t, trace.temp_filt_between, quantum, blocks)
        terms = combination_budget(w_slope, bt, bg, ph, td, noise.wander, amps, lag_sigma_s)
        terms["fit"] = var_fit
        budget[o] = terms
        sigmas[o] = np.sqrt(sum(terms.values()))
    if len(drifts) >= 2 and all(np.all(np.isfinite(sigmas[o])) for o in drifts):
        res = build_result("offline", drifts, cfg, n_runs, td_sigma=sigmas)
    else:
        res = build_result("offline", drifts, cfg, n_runs)
    res.uncertainty = _uncertainty_doc(drifts, budget, sigmas, quantum, dither, noise, lag_sigma_s)
    # TD_i is the chord of the part's response over this orientation's data: a bias curvature c2
    # (mg/C^2) adds c2 * chord_x_c to it (x = T - t_ref; 2x the data's mean x for symmetric data)
    res.uncertainty["chord_x_c"] = {str(o): v for o, v in chord_x.items() if o in drifts}
    res.wander = noise.wander  # the part's: the residual report of the same record uses it too
    res.part_noise = noise
    return res


def runs_by_orientation(use: np.ndarray, orientation: np.ndarray) -> dict[int, list[tuple[int, int]]]:
    """Per orientation, the [start, end) runs where `use` holds: `_runs(use & (orientation == o))`
    for every o at once (each run of `use` cut where the orientation changes), in one pass."""
    change = np.flatnonzero(orientation[1:] != orientation[:-1]) + 1
    out: dict[int, list[tuple[int, int]]] = {}
    for s, e in _runs(use):
        k = int(np.searchsorted(change, s, side="right"))
        while s < e:
            cut = int(change[k]) if k < change.shape[0] and change[k] < e else e
            out.setdefault(int(orientation[s]), []).append((s, cut))
            s, k = cut, k + 1
    return out


def _regression(temp: np.ndarray, acc: np.ndarray, runs: list[tuple[int, int]], t_ref_c: float,
                eiv_correction: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(TD g/C, Acc0 g, chord_x C) of one orientation's samples: acceleration = Acc0 + TD (T - t_ref)
    by least squares, the slope's errors-in-variables correction (module doc), and what the slope
    makes of a curvature c2 (c2 * chord_x). An orientation of up to ONE_PASS_SAMPLES samples (every
    orientation of a 10 h log at 3.125 Hz) is computed in one piece, as it always was, the same bits;
    a longer one (a long log) in pieces, the same to float rounding (the sums' order differs)."""
    n = sum(e - s for s, e in runs)
    if n <= ONE_PASS_SAMPLES:
        idx = np.concatenate([np.arange(s, e) for s, e in runs])
        x = temp[idx] - t_ref_c
        y = acc[idx]
        xm = x.mean()
        ym = y.mean(axis=0)
        xc = x - xm
        sxx = float(xc @ xc)
        sxy = xc @ (y - ym)
        chord = float(xc @ (x * x)) / sxx
    else:
        v = values(temp, runs)
        xm = pairwise_sum(lambda a, b: v.piece(a, b) - t_ref_c, n) / n
        ym = rows_sum((acc[a:b] for a, b in pieces(runs)), 3) / n
        sxx, sxy, sxxx = 0.0, np.zeros(3), 0.0
        for a, b in pieces(runs):
            x = temp[a:b] - t_ref_c
            xc = x - xm
            sxx += float(xc @ xc)
            sxy += xc @ (acc[a:b] - ym)
            sxxx += float(xc @ (x * x))
        chord = sxxx / sxx
    if eiv_correction:
        d = diffs(temp, runs)  # the reading's noise: var(first differences) / 2 within runs
        var_noise = 0.5 * (pairwise_sum(lambda a, b: d.piece(a, b) ** 2, d.n) / d.n) if d.n else 0.0
        sxx_true = sxx - n * var_noise
        if sxx_true > 0.5 * sxx:  # only a small correction is trusted
            sxx = sxx_true
    td = sxy / sxx  # eq. 3 as a regression slope, g/C
    return td, ym - td * xm, chord  # eq. 4: the line at T = t_ref


def part_noise_of(time_s, acc_g, runs, class_wander: BiasWander, wander: BiasWander | str | None) -> PartNoise:
    """The wander the budgets use: measured on the part for "auto" (part_noise module doc), the
    class constant as it is for "class", or the BiasWander / white-only the caller fixed."""
    if wander == "auto":
        return measure_part_noise(time_s, acc_g, runs, class_wander)
    return PartNoise(class_wander, class_wander, 1.0, 0, (float("nan"),) * 3,
                     "class" if isinstance(wander, str) else "given")


def _uncertainty_doc(drifts, budget, sigmas, quantum, dither, noise: PartNoise, lag_sigma_s) -> dict:
    """The budget behind each TD_i sigma (mg/C, per term) and the TDB/TDSF correlation per axis
    (two orientations: TDB and TDSF are both made of the same TD_i, so they are correlated)."""
    keys = sorted(drifts)
    wander = noise.wander
    out = {"temperature_quantum_c": quantum, "temperature_dither_c": dither, "wander": wander.name,
           "wander_rw_g_per_sqrt_s": wander.rw_g_per_sqrt_s, "wander_flicker_g": wander.flicker_g,
           "wander_flicker_tau_s": list(wander.flicker_tau_s), "part_noise": noise.to_json(),
           "lag_sigma_s": lag_sigma_s, "orientations": {}, "tdb_tdsf_corr": {}}
    for o in keys:
        if o in budget:
            out["orientations"][str(o)] = {term: (np.sqrt(v) * 1e3).tolist() for term, v in budget[o].items()}
    if len(keys) >= 2 and all(o in sigmas and np.all(np.isfinite(sigmas[o])) for o in keys):
        acc0 = np.array([drifts[o][1] for o in keys])
        sig = np.array([sigmas[o] for o in keys])
        for k, ax in enumerate("xyz"):
            w = 1.0 / np.maximum(sig[:, k], 1e-300) ** 2
            design = np.column_stack([np.ones(len(keys)), acc0[:, k]])
            cov = np.linalg.inv(design.T @ (design * w[:, None]))
            out["tdb_tdsf_corr"][ax] = float(cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]))
    return out


__all__ = ["offline_fit", "usable_mask", "BiasWander", "WANDER_BY_SENSOR", "NO_WANDER", "LAG_SIGMA_S", "wander_for", "white_density_ug_per_sqrt_hz",
           "characterise_bias_wander", "budget_inputs", "temperature_quantum_c", "temperature_dither_c", "quantiser_amplitudes_c",
           "block_features", "combination_budget"]
