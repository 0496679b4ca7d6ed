"""The board's own calibrator against the station's result: TDB/TDSF per axis side by side, with
the combined uncertainty each difference is judged with (issue 42, the check `board_selfcal_agrees`).

Pure: the board's reading (contracts/selfcal_opinion.py BoardSelfCalReading: its `R` result and its
`G` segments), the station's result per axis with its 1-sigma and the station's noise figures of
THIS part in; a SelfCalOpinion out.

How each uncertainty is obtained
- The station's: the offline fit's own 1-sigma (station/science/offline_fit.py, docs/verdicts.md
  "Uncertainty budget": fit scatter, the part's bias wander, the temperature quantiser, MEMS lag).
- The board's: its estimator is martinez2022 3.3's end-of-test computation on the segments it
  saved (its `G` frames: raw means of n samples, their temperature and end time). The station runs
  the same computation (drift_coefficients.result_from_segments) on those segments and takes its
  derivative with respect to every segment's mean acceleration (per axis) and mean temperature
  (central differences: the computation is a ratio of differences, linear to 1e-9 at these steps).
  The variance is that linear combination's under the station's noise model of this part:
    white     sum_j w_j^2 sigma^2 / n_j, sigma the part's per-sample white noise (its measured
              density: sigma^2 = density^2 ODR / 2; without one, the station's own segments'
              standard deviation),
    wander    -1/2 sum_ij w_i w_j D(|t_i - t_j|) with the part's bias-wander structure function D
              (the level the station's budget measured on this part's still data), each segment
              spread over 8 points of its own span so averaging inside a segment counts,
    quantiser sum_j v_j^2 sum_h A_h^2 / 2: the mean of a dithered 1 C-step reading at a steady
              temperature is off by the quantiser's periodic error (A_h from the reading's step and
              dither as the station measured them), v_j the derivative by segment j's temperature.
  A part with more wander or a coarser reading gets a wider band from its own figures, not from a
  class constant. Without `G` frames, the station's own streaming segments (the same algorithm on
  the same samples) stand in for the board's, and the opinion says so.
- Combined: u = sqrt(u_board^2 + u_station^2), i.e. the two errors taken as independent. They are
  not: both estimates are made from the same samples, so every correlated term (the wander between
  the ambient and hot data, the quantiser's bias) moves them together and cancels in their
  difference; for an efficient station estimate var(board - station) is about u_board^2 - u_station^2.
  Taking them as independent over-states the difference's sigma (never under-states it while the
  correlation is positive, which sharing samples makes it), so correlated noise widens the band and
  never fails an honest board; the price is sensitivity (a skew below about 3 u is not seen).
A figure agrees when |board - station| <= K_AGREE u; 6 figures per board, each at k = 3 on an
over-stated sigma, keeps a healthy batch's false alarms well under 1 %.

Also given, for diagnosis: the board's figure recomputed by the station from the board's own
segments (`board_from_segments`): a board whose reported result differs from its segments has
wrong arithmetic or a wrong report; one whose segments differ from the station's saw other data.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from contracts.json_safe import JsonDict, finite_or_none
from contracts.selfcal_opinion import BoardSegment, BoardSelfCalReading, OpinionRow, SelfCalOpinion
from contracts.types import AXES, AxisThermal, Segment
from station.science.bias_wander import BiasWander, wander_for
from station.science.drift_coefficients import InsufficientData, result_from_segments
from station.science.offline_fit import quantiser_amplitudes_c
from station.science.part_noise import wander_of_budget
from station.science.streaming_config import StreamingConfig

K_AGREE = 3.0  # |board - station| <= K_AGREE x combined u (module doc)
H_ACC_G = 1e-5  # central-difference steps of the derivatives (the computation is linear far beyond)
H_TEMP_C = 1e-3
SPREAD_POINTS = 8  # points a segment's span is spread over for the wander term
UINT32 = 1 << 32
ASSUMPTIONS = ("board and station errors combined as independent: they share their samples, so the correlated "
               "terms (bias wander between ambient and hot data, the temperature quantiser's bias) move both "
               "together and the true sigma of their difference is smaller: the band is conservative and "
               "correlated noise widens it, never fails an honest board")


@dataclass(frozen=True)
class PartNoiseModel:
    """The station's noise figures of this part, as the board's uncertainty uses them."""

    sample_sigma_g: tuple[float, float, float]  # per-sample white noise per axis, g
    wander: BiasWander
    temp_quantum_c: float
    temp_dither_c: float
    source: str  # where each figure comes from, in words

    def to_json(self) -> JsonDict:
        return {"sample_sigma_mg": [s * 1e3 for s in self.sample_sigma_g], "wander": self.wander.name,
                "wander_rw_g_per_sqrt_s": self.wander.rw_g_per_sqrt_s, "wander_flicker_g": self.wander.flicker_g,
                "temperature_quantum_c": self.temp_quantum_c, "temperature_dither_c": self.temp_dither_c,
                "source": self.source}


def part_noise_model(uncertainty: Mapping[str, object] | None, station_segments: Sequence[Segment], odr_hz: float,
                     sensor: str | None = None) -> PartNoiseModel:
    """The part's noise as the station measured it (its thermal result's uncertainty budget):
    white density per axis -> per-sample sigma, the wander at the part's level, the reading's step
    and dither. Where the budget lacks a figure, the next best of this part: the station's own
    segments' scatter for the white noise; the sensor class's wander only when the budget names none
    (said in `source`)."""
    unc = uncertainty or {}
    words: list[str] = []
    pn = unc.get("part_noise")
    white = pn.get("white_ug_per_sqrt_hz") if isinstance(pn, Mapping) else None
    sig: list[float] = []
    if isinstance(white, (list, tuple)) and len(white) == 3 and all(finite_or_none(w) for w in white) and odr_hz > 0:
        sig = [float(w) * 1e-6 * math.sqrt(odr_hz / 2.0) for w in white]  # density^2 = sigma^2 / (ODR / 2)
        words.append("white noise: this part's measured density")
    else:
        stds = np.array([s.acc_std_g for s in station_segments if s.n_samples > 1], dtype=np.float64).reshape(-1, 3)
        if len(stds):
            sig = [float(x) for x in np.median(stds, axis=0)]
            words.append("white noise: the station's segments' scatter on this part")
    if len(sig) != 3 or not all(math.isfinite(s) and s > 0 for s in sig):
        raise InsufficientData("no noise figure of this part (neither a measured density nor segment scatter)")
    wander = wander_of_budget(unc)
    if wander is None:
        wander = wander_for(sensor)
        words.append(f"bias wander: the {wander.name} class's (the station's budget names none)")
    else:
        src = pn.get("source") if isinstance(pn, Mapping) else None
        words.append("bias wander: the station's budget at this part's level" if src == "measured" else
                     f"bias wander: the station's budget ({src or 'source not stated'})")
    q = finite_or_none(unc.get("temperature_quantum_c")) or 0.0
    s = finite_or_none(unc.get("temperature_dither_c")) or 0.0
    return PartNoiseModel((sig[0], sig[1], sig[2]), wander, q, s, "; ".join(words))


def board_segments(segments: Sequence[BoardSegment], odr_hz: float) -> list[Segment]:
    """The board's `G` frames as the station's Segment records, in the board's order of saving:
    its 32-bit microsecond clock unwrapped in that order (a gap between two segments longer than
    the clock's 4295 s period would be undercounted by whole periods: a fast-thermal step is far
    shorter), each segment's span from its n samples at the ODR."""
    out: list[Segment] = []
    wraps, prev = 0, None
    for s in sorted(segments, key=lambda s: s.index):
        if prev is not None and s.t_end_us < prev:
            wraps += 1
        prev = s.t_end_us
        t_end = (s.t_end_us + wraps * UINT32) / 1e6
        span = max(s.n - 1, 0) / odr_hz if odr_hz > 0 else 0.0
        out.append(Segment(index=s.index, orientation=s.orientation, n_samples=s.n, t_start_s=t_end - span,
                           t_end_s=t_end, acc_mean_g=s.acc_g, acc_std_g=(0.0, 0.0, 0.0), temp_mean_c=s.temp_c,
                           temp_std_c=0.0))
    return out


def _figures(segs: list[Segment], cfg: StreamingConfig) -> np.ndarray:
    """(2, 3): TDB mg/C and TDSF ppm/C per axis of the end-of-test computation (unclamped)."""
    r = result_from_segments(segs, cfg)
    return np.array([[r.axes[a].tdb_mg_per_c for a in AXES], [r.axes[a].tdsf_ppm_per_c for a in AXES]])


def _nudged(segs: list[Segment], j: int, axis: int | None, h: float) -> list[Segment]:
    s = segs[j]
    if axis is None:
        moved = replace(s, temp_mean_c=s.temp_mean_c + h)
    else:
        acc = list(s.acc_mean_g)
        acc[axis] += h
        moved = replace(s, acc_mean_g=(acc[0], acc[1], acc[2]))
    return segs[:j] + [moved] + segs[j + 1:]


def estimator_sigmas(segs: list[Segment], noise: PartNoiseModel,
                     config: StreamingConfig | None = None) -> tuple[np.ndarray, JsonDict]:
    """(2, 3) 1-sigma of TDB (mg/C) and TDSF (ppm/C) per axis of the end-of-test computation on
    these segments under the part's noise (module doc), and the terms per figure and axis."""
    cfg = replace(config or StreamingConfig(), clamp_positive_tdsf=False)
    n = len(segs)
    w_acc = np.zeros((2, 3, n))  # d figure / d acc_j (per g) of the same axis
    w_temp = np.zeros((2, 3, n))  # d figure / d temp_j (per C)
    for j in range(n):
        for k in range(3):
            d = (_figures(_nudged(segs, j, k, H_ACC_G), cfg) - _figures(_nudged(segs, j, k, -H_ACC_G), cfg)) / (2 * H_ACC_G)
            w_acc[:, k, j] = d[:, k]
        w_temp[:, :, j] = (_figures(_nudged(segs, j, None, H_TEMP_C), cfg)
                           - _figures(_nudged(segs, j, None, -H_TEMP_C), cfg)) / (2 * H_TEMP_C)
    counts = np.array([max(s.n_samples, 1) for s in segs], dtype=np.float64)
    # each segment spread over SPREAD_POINTS points of its own span (its mean averages the wander inside)
    frac = (np.arange(SPREAD_POINTS) + 0.5) / SPREAD_POINTS
    times = np.concatenate([s.t_start_s + frac * (s.t_end_s - s.t_start_s) for s in segs])
    amps = quantiser_amplitudes_c(noise.temp_quantum_c, noise.temp_dither_c)
    var_temp_c2 = float(np.sum(amps ** 2) / 2.0)
    sig = np.zeros((2, 3))
    terms: JsonDict = {}
    for f, name in enumerate(("tdb_mg_per_c", "tdsf_ppm_per_c")):
        per_axis: JsonDict = {}
        for k, ax in enumerate(AXES):
            w = w_acc[f, k]
            white = float(np.sum(w ** 2 / counts)) * noise.sample_sigma_g[k] ** 2
            wander = noise.wander.combination_var_g2(np.repeat(w / SPREAD_POINTS, SPREAD_POINTS), times)
            quant = float(np.sum(w_temp[f, k] ** 2)) * var_temp_c2
            sig[f, k] = math.sqrt(white + wander + quant)
            per_axis[ax] = {"white": math.sqrt(white), "wander": math.sqrt(wander), "quantiser": math.sqrt(quant)}
        terms[name] = per_axis
    return sig, terms


def compare(reading: BoardSelfCalReading, station_axes: Mapping[str, AxisThermal],
            uncertainty: Mapping[str, object] | None, station_segments: Sequence[Segment], odr_hz: float,
            sensor: str | None = None, k: float = K_AGREE) -> SelfCalOpinion:
    """The opinion of one run (module doc). Never raises for what the data lack: a board without a
    calibrator is not applicable, a capable board without a usable result is an error opinion."""
    n_st = len(station_segments)
    if not reading.capable:
        return SelfCalOpinion(False, note=reading.note or "the board reports no on-board calibrator",
                              n_segments_station=n_st)
    if not reading.has_result:
        return SelfCalOpinion(True, error=reading.error or "the board gave no result", n_segments_station=n_st,
                              n_segments_board=reading.n_segments)
    assert reading.tdb_mg_per_c is not None and reading.tdsf_ppm_per_c is not None
    missing = [a for a in AXES if a not in station_axes]
    if missing:
        return SelfCalOpinion(True, error=f"the station has no result for axis {', '.join(missing)}",
                              n_segments_board=reading.n_segments, n_segments_station=n_st)
    try:
        noise = part_noise_model(uncertainty, station_segments, odr_hz, sensor)
    except InsufficientData as exc:
        return SelfCalOpinion(True, error=f"the board's uncertainty cannot be told: {exc}",
                              n_segments_board=reading.n_segments, n_segments_station=n_st)
    from_board = board_segments(reading.segments, odr_hz)
    segs, seg_words = (from_board, f"the board's {len(from_board)} G segment(s)") if from_board else \
        (list(station_segments), f"the station's {n_st} streaming segment(s) standing in for the board's "
                                 "(the board sent no G frames)")
    recomputed: np.ndarray | None = None
    try:
        sig, terms = estimator_sigmas(segs, noise)
        if from_board:
            r = result_from_segments(from_board, StreamingConfig())
            recomputed = np.array([[r.axes[a].tdb_mg_per_c for a in AXES], [r.axes[a].tdsf_ppm_per_c for a in AXES]])
    except InsufficientData as exc:
        return SelfCalOpinion(True, error=f"the board's segments do not give its estimate ({exc})",
                              n_segments_board=reading.n_segments, n_segments_station=n_st,
                              noise=noise.to_json())
    rows: list[OpinionRow] = []
    for k_ax, ax in enumerate(AXES):
        st = station_axes[ax]
        for f, (name, board_val, station_val, st_sig) in enumerate((
                ("tdb_mg_per_c", reading.tdb_mg_per_c[k_ax], st.tdb_mg_per_c, st.tdb_sigma_mg_per_c),
                ("tdsf_ppm_per_c", reading.tdsf_ppm_per_c[k_ax], st.tdsf_ppm_per_c, st.tdsf_sigma_ppm_per_c))):
            rows.append(OpinionRow(ax, name, float(board_val), float(station_val), float(sig[f, k_ax]),
                                   None if st_sig is None else float(st_sig), k,
                                   None if recomputed is None else float(recomputed[f, k_ax]),
                                   clamped_board=bool(reading.clamped_axes[k_ax]) if f == 1 else False,
                                   clamped_station=bool(st.tdsf_clamped) if f == 1 else False))
    noise_doc = noise.to_json()
    noise_doc["board_estimate_from"] = seg_words
    noise_doc["terms"] = terms
    return SelfCalOpinion(True, tuple(rows), n_segments_board=reading.n_segments, n_segments_station=n_st,
                          noise=noise_doc, assumptions=ASSUMPTIONS)


def opinion_words(op: SelfCalOpinion) -> str:
    """The opinion in one line for the operator (the verdict's reason)."""
    if not op.applicable:
        return f"board's own calibrator: not applicable ({op.note})"
    if op.error is not None:
        return f"board's own calibrator: no comparison: {op.error}"
    bad = [r for r in op.rows if not r.agrees]
    if not bad:
        worst = max(op.rows, key=lambda r: abs(r.difference) / max(r.u_combined, 1e-300))
        return (f"board's own calibrator agrees with the station on every axis (largest difference "
                f"{abs(worst.difference) / max(worst.u_combined, 1e-300):.1f} x the combined u, limit {worst.k:g})")
    return "board's own calibrator disagrees: " + "; ".join(row_words(r) for r in bad)


def row_words(r: OpinionRow) -> str:
    """One figure side by side: 'x TDB board 0.612, station 0.498 +-0.004 mg/C: differ +0.114 = 19.0 u (u 0.006, 1 sigma; limit 3 u)'."""
    st_sig = "" if r.u_station is None else f" +-{r.u_station:.3g}"
    ratio = abs(r.difference) / max(r.u_combined, 1e-300)
    seg = r.board_from_segments
    own = f"; its own G segments give {seg:.4g}: its result, not its data, is off" \
        if seg is not None and abs(seg - r.board) > max(0.1 * r.u_combined, 1e-4 * abs(r.board)) else ""
    return (f"{r.axis} {r.label} board {r.board:.4g}, station {r.station:.4g}{st_sig} {r.unit}: differ "
            f"{r.difference:+.3g} = {ratio:.1f} u (u {r.u_combined:.2g}, 1 sigma; limit {r.k:g} u){own}")


__all__ = ["K_AGREE", "PartNoiseModel", "part_noise_model", "board_segments", "estimator_sigmas", "compare",
           "opinion_words", "row_words", "ASSUMPTIONS"]
