"""Shaping one DUT's calibration result from what its run collected (pure: a DutRun in, JSON out).

Thermal: the offline fit (station/science/thermal_calibration.calibrate) over the run's samples at
its logged segments, beside the live streaming calibrator's own result, as `station calibrate
--json` prints it. SFEM: one sensor-frame fit per temperature step, from the static window of each
position (sensors2023). Both run in a worker thread while the pump may still append blocks, so
they work on a snapshot of the block list.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from contracts.json_safe import plain_json
from contracts.positions import GRAVITY_DIRECTIONS
from contracts.types import SampleBlock, StationError
from station.daemon.dut_run import DutRun
from station.profiles import Profile
from station.science import sfem
from station.science.thermal_calibration import calibrate, fit_samples


def thermal_result(d: DutRun, operating_range_c: float = 70.0) -> dict:
    """Streaming (the live calibrator) and offline results of one DUT, as `station calibrate --json`."""
    # list() first: a copy (atomic under the GIL) keeps the three columns of concat from seeing
    # different lists while the pump appends
    block = fit_samples(SampleBlock.concat(list(d.blocks)), [s.t_end_s for s in d.segments])
    res = dict(calibrate(block, operating_range_c=operating_range_c))
    res["serial"] = d.serial
    try:
        res["streaming_live"] = d.calibrator.result().to_json()
    except Exception as exc:
        res["streaming_live"] = {"error": str(exc)}
    res["n_samples"] = int(len(block))
    return plain_json(res)


def sfem_result(d: DutRun, profile: Profile) -> dict:
    """SFEM per temperature step from the static windows of each step (sensors2023)."""
    groups: dict[Any, list[int]] = {}
    for i, s in enumerate(profile.steps):
        if s.require == "static":
            groups.setdefault((s.chamber_setpoint_c, s.lamp), []).append(i)
    full = SampleBlock.concat(list(d.blocks))  # a snapshot: the pump may still append (worker thread)
    out: dict = {"temperatures": []}
    for (setpoint, lamp), idxs in groups.items():
        means, refs, temps = [], [], []
        for i in idxs:
            if i not in d.step_windows:
                continue
            t_from, t_to = d.step_windows[i]
            s = profile.steps[i]
            lo = t_from + s.settle_s
            m = (full.time_s > lo) & (full.time_s <= min(t_to, lo + s.dwell_s))
            if m.sum() < 10:
                continue
            means.append(full.acc_g[m].mean(axis=0))
            temps.append(float(full.temp_c[m].mean()))
            refs.append(GRAVITY_DIRECTIONS[s.position])
        if len(means) < 9:
            continue
        fit = sfem.fit_sfem(np.array(means), ref_dir=np.array(refs))
        fj = fit.to_json() if hasattr(fit, "to_json") else plain_json(fit)
        out["temperatures"].append({"setpoint_c": setpoint, "lamp": lamp, "temp_c": float(np.mean(temps)),
                                    "n_positions": len(means), "fit": fj})
    if not out["temperatures"]:
        raise StationError("no temperature step has enough static positions for an SFEM fit")
    return plain_json(out)
