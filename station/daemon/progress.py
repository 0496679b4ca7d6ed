"""How far a batch has come and how long it still needs: what GET /api/batches/{id} adds to the
sequencer's own status (decision summary, sorting list for the trays, time left).

Time left is an estimate from the plant's own behaviour in this batch (the calibrator's state and
the temperature trend for segment steps, dwell for static ones, the completed steps of the same
kind for those to come); it can never break the status.
"""

from __future__ import annotations

import math
import time
from typing import Any

from station.daemon.states import TERMINAL
from station.decisions.verdicts import summarize


def _segment_step_need_s(d: Any, odr_hz: float) -> float | None:
    """Sample seconds this DUT still needs to log a segment, from its calibrator's state and the
    temperature trend (the filtered gradient must fall under the limit first)."""
    cal = d.calibrator
    if cal is None:
        return None
    c = cal.config
    st = getattr(cal, "state", "settling")
    n_disc = int(getattr(cal, "_n_disc", 0))
    n_avg = int(getattr(cal, "_n_avg", 0))
    need = (max(0, c.discard_samples - n_disc) + max(0, c.average_samples - n_avg)) / odr_hz
    if st == "settling":
        g = abs(float(getattr(cal, "gradient_c_per_min", 0.0)))
        lim = float(c.gradient_limit_c_per_min)
        tau_s = _gradient_tau_s(d, g)
        if g > lim:
            need += tau_s * math.log(g / lim)
    return need


def _gradient_tau_s(d: Any, g: float, default_s: float = 300.0) -> float:
    """Time constant of the gradient's decay from two looks at least 30 sample seconds apart
    (the plate approaches its temperature exponentially); a default until the trend is known."""
    now = d.last_t or 0.0
    hist = d.__dict__.setdefault("_grad_hist", [])
    if not hist or now - hist[-1][0] >= 30.0:
        hist.append((now, g))
        del hist[:-2]
    if len(hist) == 2:
        (t1, g1), (t2, g2) = hist
        if g2 > 0 and g1 > g2 and t2 > t1:
            return min(3600.0, max(30.0, (t2 - t1) / math.log(g1 / g2)))
    return default_s


def time_left(station: Any, seq: Any) -> dict:
    """Estimated sample and wall seconds left in the step and the batch.

    Step: the slowest pending DUT's need (segment: calibrator state + temperature trend; static /
    none: dwell left), capped by the step timeout. Later steps: static/none their settle + dwell;
    segment steps the mean duration of this batch's completed segment steps of the same kind
    (changing the plate temperature or not; else half the timeout), capped by their timeouts.
    Wall = sample time / the configured speed."""
    steps = seq.profile.steps
    speed = float(station.config.timing.speed) or 1.0
    if seq.state in TERMINAL or seq.step is None:
        return {"step_s": 0.0 if seq.state in TERMINAL else None, "batch_s": 0.0 if seq.state in TERMINAL else None,
                "step_wall_s": None, "batch_wall_s": None}
    step = seq.step
    elapsed = max(0.0, seq.clock_s() - seq.step_clock_start) if seq.state == "logging" else 0.0
    needs = []
    for d in seq.live_duts:
        if seq.state == "logging" and seq.dut_step_done(d, step):
            continue
        odr = float(getattr(d.identity, "odr_hz", 0) or 3.125)
        if step.require == "segment":
            n = _segment_step_need_s(d, odr)
        else:
            n = max(0.0, step.dwell_s + (step.settle_s if step.require == "static" else 0.0) - elapsed)
        if n is not None:
            needs.append(n)
    step_left = min(max(needs, default=0.0), max(0.0, step.timeout_s - elapsed))
    def heats(i: int) -> bool:  # the step changes the plate's temperature (lamp or set point)
        prev_lamp, prev_sp = (steps[i - 1].lamp, steps[i - 1].chamber_setpoint_c) if i > 0 else (False, None)
        return steps[i].lamp != prev_lamp or steps[i].chamber_setpoint_c != prev_sp

    done: dict[bool, list[float]] = {True: [], False: []}
    for i in range(seq.step_index):
        if steps[i].require != "segment":
            continue
        spans = [d.step_windows[i] for d in seq.duts if i in d.step_windows and math.isfinite(d.step_windows[i][0])]
        done[heats(i)] += [b - a for a, b in spans]
    rest = 0.0
    for i in range(seq.step_index + 1, len(steps)):
        s = steps[i]
        if s.require == "segment":
            # like the completed steps of the same kind (temperature change or not), else half the timeout
            seen = done[heats(i)]
            rest += min(s.timeout_s, sum(seen) / len(seen) if seen else s.timeout_s / 2)
        else:
            rest += min(s.timeout_s, s.settle_s + s.dwell_s)
    batch_left = step_left + rest
    return {"step_s": step_left, "batch_s": batch_left, "step_wall_s": step_left / speed,
            "batch_wall_s": batch_left / speed, "estimated_at": time.time()}


def batch_extras(station: Any, seq: Any) -> dict:
    """Decision summary, sorting list and time left for GET /api/batches/{id}."""
    verdicts = [getattr(d, "verdict", None) for d in seq.duts]
    sorting = [
        {"slot": d.slot, "serial": d.serial, "verdict": v.get("verdict"), "grade": v.get("grade"), "tray": v.get("tray"),
         "reason": v.get("reason"), "attempt": v.get("attempt")}
        for d, v in zip(seq.duts, verdicts) if v
    ]
    try:
        left = time_left(station, seq)
    except Exception as exc:  # noqa: BLE001 - an estimate must never break the status
        left = {"error": f"{type(exc).__name__}: {exc}"}
    return {"decision": summarize(verdicts), "sorting": sorting, "time_left": left}
