"""Thermal calibration of one DUT record with both methods: the JSON of `station calibrate --json`.

The streaming calibrator (martinez2022 3.3, what the MCU/daemon runs live) and the offline fit
(regression over all stable data, Table 5 "Regr.") run on the same samples. The top-level "axes"
holds the OFFLINE values: they use every stable sample instead of two 1000-sample averages per
orientation and carry 1-sigma uncertainties, so they are the better estimate; the streaming values
are kept beside them for comparison and for what a board would compute itself.

The offline sigmas are the whole budget (docs/verdicts.md "Uncertainty budget"), not the fit's
scatter alone: the part's bias wander between segments (its sensor class, by name or by its white
noise), the temperature quantiser and the MEMS lag; "uncertainty" in the JSON holds the terms.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, replace

import numpy as np
from scipy.signal import lfilter

from contracts.logfile import DutLog
from station.science.chunked import keep_rows, pieces
from station.science.offline_fit import offline_fit
from station.science.placement import settled_labels
from station.science.residual import DEFAULT_OPERATING_RANGE_C, residual_report
from station.science.drift_coefficients import InsufficientData, result_from_segments
from station.science.gate_trace import trace_gate
from station.science.streaming_config import StreamingConfig
from contracts.types import AXES, SampleBlock, Segment, StationError

AXES_METHOD = "offline"


def _filtered_swing_c(temp_c: np.ndarray, alpha: float) -> float:
    """Temperature swing of the filtered reading (one noisy sample does not make a swing). In pieces,
    the filter's state carried between them: the same outputs as one call, no copy of the record."""
    zi = [(1.0 - alpha) * temp_c[0]]
    lo, hi = np.inf, -np.inf
    for a, b in pieces([(0, temp_c.shape[0])]):
        f, zi = lfilter([alpha], [1.0, -(1.0 - alpha)], temp_c[a:b], zi=zi)
        lo, hi = min(lo, np.min(f)), max(hi, np.max(f))
    return float(hi - lo)


def _small_codes(position: np.ndarray) -> np.ndarray:
    """The position codes as int8 when they fit (-1 and the contract's indices always do): the same
    values in an eighth of the memory."""
    lo_hi = (int(position.min()), int(position.max())) if position.size else (0, 0)
    return position.astype(np.int8) if -128 <= lo_hi[0] and lo_hi[1] <= 127 else position


def _all_finite(*arrays: np.ndarray) -> bool:
    return all(bool(np.all(np.isfinite(x[a:b]))) for x in arrays for a, b in pieces([(0, x.shape[0])]))


def _with_positions(segments: list[Segment], time_s: np.ndarray, position: np.ndarray | None) -> list[Segment]:
    if position is None:
        return segments
    ordered = bool(np.all(time_s[1:] >= time_s[:-1]))  # then a segment's samples are one slice
    out = []
    for s in segments:
        if ordered:
            vals = position[np.searchsorted(time_s, s.t_start_s, "left"):np.searchsorted(time_s, s.t_end_s, "right")]
        else:
            vals = position[(time_s >= s.t_start_s) & (time_s <= s.t_end_s)]
        vals = vals[vals >= 0]
        out.append(replace(s, position=int(Counter(vals.tolist()).most_common(1)[0][0])) if vals.size else s)
    return out


def placed_only(block: SampleBlock, position: np.ndarray | None,
                in_place: bool = False) -> tuple[SampleBlock, np.ndarray | None]:
    """The samples the station placed at a position (station/science/placement.py): a log with a
    position column drops its -1 rows (the plate being turned, not yet settled, or not where the
    step wanted it) and the rows whose samples do not show the labelled position settled (a
    producer that labelled by a button), so a stored log, a third-party log and the station's own
    analysis fit the samples the station would. A log without placed rows keeps everything.
    in_place: the placed rows are moved to the front of the block's own arrays, which are returned
    cut to them (no copy: a long log's command owns its arrays; the block is spent afterwards)."""
    if position is None:
        return block, None
    pos = np.asarray(position).reshape(-1)
    if not (pos >= 0).any():
        return block, pos
    own = in_place and pos.dtype == np.int64  # the labels over the column itself: one array, not two
    pos = settled_labels(block.time_s, block.acc_g, pos, out=pos if own else None)  # the station's labels pass unchanged
    keep = pos >= 0
    if keep.all():
        return block, pos
    if in_place:
        t, acc, temp, pos = keep_rows(keep, block.time_s, block.acc_g, block.temp_c, pos)
        return SampleBlock(t, acc, temp), pos
    return SampleBlock(block.time_s[keep], block.acc_g[keep], block.temp_c[keep]), pos[keep]


def fit_samples(block: SampleBlock, segment_ends_s: list[float]) -> SampleBlock:
    """The samples a DUT's fit uses: up to the end of its last segment. What a station receives
    after it (while other DUTs finish the step and the batch stops) depends on wall-clock latency,
    i.e. on CPU load and compressed time; a result must depend on the data only, so that a replay
    of the same samples (station replay) gives the same numbers."""
    if not segment_ends_s or not len(block):
        return block
    keep = block.time_s <= max(float(t) for t in segment_ends_s)
    return SampleBlock(block.time_s[keep], block.acc_g[keep], block.temp_c[keep], block.lost_samples)


def calibrate(block_or_log: DutLog | SampleBlock, config: StreamingConfig | None = None,
              operating_range_c: float = DEFAULT_OPERATING_RANGE_C, wander: str = "auto", *,
              consume_log: bool = False) -> dict:
    """Both methods on one record; raises StationError (InsufficientData) with one clear line.

    wander: "auto" (the part's measured noise level, the station's) or "class" (the sensor class's
    constant, for comparison: benchmarks/coverage.py --wander class).
    consume_log: the DutLog's arrays may be overwritten (its placed rows moved to their front,
    placed_only in_place): `station calibrate` reads a log for this call alone, and a long log then
    costs no second copy of its placed rows. The log is not to be used afterwards.
    "residual" holds what the offline TDB/TDSF leave over `operating_range_c` (station/science/
    residual.py: drift error E/E_FS of eqs. 10-12 with its 1-sigma, curvature, noise density)."""
    cfg = config or StreamingConfig()
    serial, sensor, position = "", "", None
    if isinstance(block_or_log, DutLog):
        log = block_or_log
        del block_or_log  # the log's last reference may be here (consume_log): `block` keeps its arrays
        serial, sensor = log.serial, log.meta.get("sensor", "")
        block, position = placed_only(log.block(), log.position, in_place=consume_log)
        del log
        if consume_log and position is not None:
            position = _small_codes(position)  # 1 byte a sample; the log's 8-byte column is then freed
    else:
        block = block_or_log
    n = len(block)
    need = cfg.discard_samples + cfg.average_samples
    if n < 4 * need:
        raise InsufficientData(
            f"only {n} samples: a fast-thermal calibration needs four segments of "
            f"{cfg.discard_samples}+{cfg.average_samples} stable samples"
        )
    if not _all_finite(block.acc_g, block.temp_c, block.time_s):
        raise InsufficientData("the log holds non-numeric (nan/inf) samples")
    swing = _filtered_swing_c(block.temp_c, cfg.alpha_acc)
    if swing < cfg.segment_delta_c:
        raise InsufficientData(
            f"temperature swing is {swing:.1f} C, below the {cfg.segment_delta_c:g} C the method needs "
            "between segments (was the lamp on?)"
        )
    trace, segments = trace_gate(block.time_s, block.acc_g, block.temp_c, cfg)
    segments = _with_positions(segments, block.time_s, position)
    try:
        streaming = result_from_segments(segments, cfg)
    except InsufficientData as exc:
        per_o = Counter(s.orientation for s in segments)
        raise InsufficientData(
            f"{len(segments)} segment(s) logged ({', '.join(f'orientation {o}: {c}' for o, c in sorted(per_o.items())) or 'none'}); "
            f"need at least two segments in each of two orientations ({exc})"
        ) from None
    # the part's bias wander (its class by sensor, else by its white noise, at the level measured on
    # its own still runs: station/science/part_noise.py) enters the coefficient sigmas
    offline = offline_fit(block.time_s, block.acc_g, block.temp_c, cfg, trace=trace, sensor=sensor or None,
                          wander=wander)
    oj = offline.to_json()["axes"]
    unc = getattr(offline, "uncertainty", {}) or {}
    residual = residual_report(
        block.time_s, block.acc_g, block.temp_c,
        [oj[a]["tdb_mg_per_c"] for a in AXES], [oj[a]["tdsf_ppm_per_c"] for a in AXES],
        [oj[a]["tdb_sigma_mg_per_c"] for a in AXES], [oj[a]["tdsf_sigma_ppm_per_c"] for a in AXES],
        operating_range_c=operating_range_c, config=cfg, trace=trace,
        tdb_tdsf_corr=[unc.get("tdb_tdsf_corr", {}).get(a) for a in AXES], sensor=sensor or None,
        wander=getattr(offline, "wander", "auto"),  # one class per record, chosen once by the fit
    )
    out = {
        "serial": serial,
        "sensor": sensor,
        "axes_method": AXES_METHOD,
        "axes": {name: dict(offline.to_json()["axes"][name]) for name in AXES},
        "streaming": streaming.to_json(),
        "offline": offline.to_json(),
        "segments": [asdict(s) for s in segments],
        "n_samples": n,
        "temperature_swing_c": swing,
        "config": asdict(cfg),
        "residual": residual,
        "uncertainty": unc,  # the budget behind the offline sigmas (offline_fit module doc)
    }
    for s in out["segments"]:
        s["acc_mean_g"] = list(s["acc_mean_g"])
        s["acc_std_g"] = list(s["acc_std_g"])
    return out


__all__ = ["calibrate", "AXES_METHOD"]
