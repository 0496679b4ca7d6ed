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
from station.science.offline_fit import offline_fit
from station.science.placement import settled_labels
from station.science.residual import DEFAULT_OPERATING_RANGE_C, residual_report
from station.science.drift_coefficients import InsufficientData, result_from_segments
from station.science.gate_trace import trace_gate
from station.science.streaming_config import StreamingConfig
from contracts.types import AXES, SampleBlock, Segment, StationError

AXES_METHOD = "offline"


def _filtered_swing_c(temp_c: np.ndarray, alpha: float) -> float:
    """Temperature swing of the filtered reading (one noisy sample does not make a swing)."""
    f, _ = lfilter([alpha], [1.0, -(1.0 - alpha)], temp_c, zi=[(1.0 - alpha) * temp_c[0]])
    return float(np.max(f) - np.min(f))


def _with_positions(segments: list[Segment], time_s: np.ndarray, position: np.ndarray | None) -> list[Segment]:
    if position is None:
        return segments
    out = []
    for s in segments:
        sel = (time_s >= s.t_start_s) & (time_s <= s.t_end_s)
        vals = position[sel]
        vals = vals[vals >= 0]
        out.append(replace(s, position=int(Counter(vals.tolist()).most_common(1)[0][0])) if vals.size else s)
    return out


def placed_only(block: SampleBlock, position: np.ndarray | None) -> tuple[SampleBlock, np.ndarray | None]:
    """The samples the station placed at a position (station/science/placement.py): a log with a
    position column drops its -1 rows (the plate being turned, not yet settled, or not where the
    step wanted it) and the rows whose samples do not show the labelled position settled (a
    producer that labelled by a button), so a stored log, a third-party log and the station's own
    analysis fit the samples the station would. A log without placed rows keeps everything."""
    if position is None:
        return block, None
    pos = np.asarray(position).reshape(-1)
    if not (pos >= 0).any():
        return block, pos
    pos = settled_labels(block.time_s, block.acc_g, pos)  # the station's labels pass unchanged
    keep = pos >= 0
    if keep.all():
        return block, pos
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
              operating_range_c: float = DEFAULT_OPERATING_RANGE_C, wander: str = "auto") -> dict:
    """Both methods on one record; raises StationError (InsufficientData) with one clear line.

    wander: "auto" (the part's measured noise level, the station's) or "class" (the sensor class's
    constant, for comparison: benchmarks/coverage.py --wander class).
    "residual" holds what the offline TDB/TDSF leave over `operating_range_c` (station/science/
    residual.py: drift error E/E_FS of eqs. 10-12 with its 1-sigma, curvature, noise density)."""
    cfg = config or StreamingConfig()
    serial, sensor, position = "", "", None
    if isinstance(block_or_log, DutLog):
        serial, sensor = block_or_log.serial, block_or_log.meta.get("sensor", "")
        block, position = placed_only(block_or_log.block(), block_or_log.position)
    else:
        block = block_or_log
    n = len(block)
    need = cfg.discard_samples + cfg.average_samples
    if n < 4 * need:
        raise InsufficientData(
            f"only {n} samples: a fast-thermal calibration needs four segments of "
            f"{cfg.discard_samples}+{cfg.average_samples} stable samples"
        )
    if not (np.all(np.isfinite(block.acc_g)) and np.all(np.isfinite(block.temp_c)) and np.all(np.isfinite(block.time_s))):
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
