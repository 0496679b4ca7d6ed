"""The built-in step kinds (station/steps/base.py StepKind), registered on import.

  segment  the DUT's streaming calibrator completes a segment after the step started, at this
           step's position (martinez2022: stable temperature, 500 discarded + 1000 averaged samples)
  static   the DUT logs `dwell_s` of sample time at this position after `settle_s` (SFEM, six-position)
  none     the step just lasts `dwell_s` of sample time (a soak, a lamp-off cool-down)
  program  program and verify, part 1 (design 4): the thermal analysis runs, then every live DUT
           with a thermal result gets its coefficients written, read back (CRC and values) and its
           on-board compensation switched on; a DUT whose write fails is faulted alone. After an
           SFEM analysis, the boards that store the version-2 record get the cubic SFEM instead
           (station/daemon/sfem_program.py; the others are not programmed)
  heat     program and verify, part 2: the lamp heats the plate again until every DUT's own
           temperature has risen `heat_c` (>= 15 C) above where the step started, while the station
           logs the boards' COMPENSATED output; `settle_s` at the start is not judged. The verified
           drift error E (station.science.verify) is computed when the batch is analysed.

The dwell and the rise count from the first placed sample (station/science/placement.py,
DutRun.requirement_window).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from station.daemon.dut_run import DutRun
from station.steps.base import Estimates, Step, StepKind, heats, register

PROGRAM_WALL_S = 8.0  # wall seconds to write, read back and restart a board (design 4; all DUTs in parallel)


class Segment(StepKind):
    name = "segment"
    summary = "the streaming calibrator completes a segment at the step's position"
    waits_for = "segment"
    counts_before_crash = True

    def done(self, d: DutRun, step: Step, index: int) -> bool:
        return any(st == index and seg.position == step.position and seg.t_end_s > d.segment_after_t()
                   for seg, st in zip(d.segments, d.segment_steps))

    def need_words(self, step: Step) -> str:
        return "a segment"

    def window_start(self, d: DutRun) -> float:
        return d.step_t_start

    def expected_s(self, step: Step, i: int, est: Estimates) -> tuple[float, float]:
        """As long as the completed segment steps of the same sort (changing the temperature or
        not) took in this batch; half the timeout until one was seen."""
        seen = [x for j in range(est.completed) if est.steps[j].require == self.name
                and heats(est.steps, j) == heats(est.steps, i) for x in est.spans(j)]
        return min(step.timeout_s, sum(seen) / len(seen) if seen else step.timeout_s / 2), 0.0

    def left_s(self, step: Step, d: DutRun, elapsed_s: float, expected_s: float, est: Estimates) -> float | None:
        odr = float(getattr(d.identity, "odr_hz", 0) or 3.125)
        return _segment_need_s(d, odr)


class Static(StepKind):
    name = "static"
    summary = "dwell_s sample seconds at the step's position after settle_s"
    waits_for = "static dwell"

    def check(self, steps: Sequence[Step], i: int, analysis: str) -> None:
        s = steps[i]
        if s.dwell_s <= 0:
            raise ValueError(f"steps[{i}]: require={s.require!r} needs dwell_s > 0")
        if s.settle_s + s.dwell_s >= s.timeout_s:
            raise ValueError(f"steps[{i}]: settle_s + dwell_s must be shorter than timeout_s")

    def done(self, d: DutRun, step: Step, index: int) -> bool:
        w = d.requirement_window()
        return w is not None and w[1] - w[0] >= step.dwell_s + step.settle_s

    def need_words(self, step: Step) -> str:
        return f"{step.dwell_s:g} s static"

    def left_s(self, step: Step, d: DutRun, elapsed_s: float, expected_s: float, est: Estimates) -> float | None:
        return step.dwell_s + step.settle_s - elapsed_s


class Dwell(StepKind):
    name = "none"
    summary = "the step lasts dwell_s sample seconds"
    waits_for = "dwell"

    def check(self, steps: Sequence[Step], i: int, analysis: str) -> None:
        if steps[i].dwell_s <= 0:
            raise ValueError(f"steps[{i}]: require={steps[i].require!r} needs dwell_s > 0")

    def done(self, d: DutRun, step: Step, index: int) -> bool:
        w = d.requirement_window()
        return w is not None and w[1] - w[0] >= step.dwell_s

    def need_words(self, step: Step) -> str:
        return "its dwell"

    def left_s(self, step: Step, d: DutRun, elapsed_s: float, expected_s: float, est: Estimates) -> float | None:
        return step.dwell_s - elapsed_s


class Program(StepKind):
    """Logs nothing: the sequencer's 'programming' state runs it (Hardware.program_duts)."""

    name = "program"
    summary = "program and verify, part 1: coefficients written, read back, compensation on"
    waits_for = "programming"
    row_kind = "program"
    configurable = False  # [profiles.NAME.program_verify] adds it (profiles.with_program_verify)
    machine_state = "programming"

    def check(self, steps: Sequence[Step], i: int, analysis: str) -> None:
        if analysis not in ("thermal", "sfem"):
            raise ValueError(f"steps[{i}]: a program step needs analysis='thermal' or 'sfem' (coefficients to write)")

    def done(self, d: DutRun, step: Step, index: int) -> bool:
        return True  # never asked: the step logs nothing

    def need_words(self, step: Step) -> str:
        return "its programming"

    def window_start(self, d: DutRun) -> float:
        return d.last_t if d.last_t is not None else -math.inf  # a program step spans no samples

    def expected_s(self, step: Step, i: int, est: Estimates) -> tuple[float, float]:
        return 0.0, PROGRAM_WALL_S

    def left_s(self, step: Step, d: DutRun, elapsed_s: float, expected_s: float, est: Estimates) -> float | None:
        return None


class Heat(StepKind):
    name = "heat"
    summary = "program and verify, part 2: every DUT's own temperature rises heat_c"
    waits_for = "temperature rise"
    row_kind = "verify"
    configurable = False  # [profiles.NAME.program_verify] adds it (profiles.with_program_verify)
    gated = True

    def check(self, steps: Sequence[Step], i: int, analysis: str) -> None:
        s = steps[i]
        if s.heat_c < 15.0:
            raise ValueError(f"steps[{i}]: a verification must heat at least 15 C (heat_c), got {s.heat_c:g}")
        if not s.lamp and s.chamber_setpoint_c is None:
            raise ValueError(f"steps[{i}]: a heat step needs the lamp on or a chamber set point")
        if not any(p.require == Program.name for p in steps[:i]):
            raise ValueError(f"steps[{i}]: a verification (heat) step must follow a program step")

    def done(self, d: DutRun, step: Step, index: int) -> bool:
        w = d.requirement_window()
        return w is not None and w[1] - w[0] >= step.settle_s and d.temp_rise_c(w[0]) >= step.heat_c

    def need_words(self, step: Step) -> str:
        return f"a +{step.heat_c:g} C rise"

    def expected_s(self, step: Step, i: int, est: Estimates) -> tuple[float, float]:
        rate = est.heating_rate_c_per_s
        return (min(step.timeout_s, step.settle_s + step.heat_c / rate) if rate else step.timeout_s / 2), 0.0

    def left_s(self, step: Step, d: DutRun, elapsed_s: float, expected_s: float, est: Estimates) -> float | None:
        rate = est.heating_rate_c_per_s
        rise = d.temp_rise_c(d.step_t_start) if math.isfinite(d.step_t_start) else 0.0
        return max(step.settle_s - elapsed_s, (step.heat_c - rise) / rate) if rate else expected_s - elapsed_s


def _segment_need_s(d: DutRun, odr_hz: float) -> float | None:
    """Sample seconds this DUT still needs to log a segment, from its calibrator's state and the
    temperature trend (the filtered gradient must fall under the limit first)."""
    cal = d.calibrator
    if cal is None:
        return None
    c = getattr(cal, "config")
    st = getattr(cal, "state", "settling")
    n_disc = int(getattr(cal, "_n_disc", 0))
    n_avg = int(getattr(cal, "_n_avg", 0))
    need = float((max(0, c.discard_samples - n_disc) + max(0, c.average_samples - n_avg)) / odr_hz)
    if st == "settling":
        g = abs(float(getattr(cal, "gradient_c_per_min", 0.0)))
        lim = float(c.gradient_limit_c_per_min)
        tau_s = _gradient_tau_s(d, g)
        if g > lim:
            need += tau_s * math.log(g / lim)
    return need


def _gradient_tau_s(d: DutRun, g: float, default_s: float = 300.0) -> float:
    """Time constant of the gradient's decay from two looks at least 30 sample seconds apart
    (the plate approaches its temperature exponentially); a default until the trend is known."""
    now = d.last_t or 0.0
    hist: list[tuple[float, float]] = d.__dict__.setdefault("_grad_hist", [])
    if not hist or now - hist[-1][0] >= 30.0:
        hist.append((now, g))
        del hist[:-2]
    if len(hist) == 2:
        (t1, g1), (t2, g2) = hist
        if g2 > 0 and g1 > g2 and t2 > t1:
            return min(3600.0, max(30.0, (t2 - t1) / math.log(g1 / g2)))
    return default_s


for _kind in (Segment(), Static(), Dwell(), Program(), Heat()):
    register(_kind)
