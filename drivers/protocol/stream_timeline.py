"""A board's sample stream as one timeline: its wrapping seq and its clock (design 3.1, 3.2).

Pure bookkeeping, no I/O and no frame format: SeqTracker counts the samples lost to seq gaps (both
links: a serial frame's 32-bit seq, a CAN frame's 8-bit one); ClockUnwrapper joins a 32-bit board
clock across its wrap; StreamTimeline tells a gap from a board that restarted or whose clock
jumped while streaming. drivers/protocol/serial_frames.py re-exports all three (their first home).
"""

from __future__ import annotations


class SeqTracker:
    """Counts samples lost to gaps in a wrapping sequence number and extends it to an index.

    A forward jump of less than half the range is a gap (lost samples); a backward jump (board
    reset, restart) resynchronises without counting. `index` is the extended (unwrapped) sequence
    number, continuous across wraps.
    """

    def __init__(self, bits: int) -> None:
        self.mod = 1 << bits
        self.half = self.mod >> 1
        self.last: int | None = None
        self.index: int = 0
        self.lost: int = 0
        self.resyncs: int = 0

    def reset(self) -> None:
        self.last = None

    def update(self, seq: int) -> int:
        """Feed the next received seq; returns the samples lost just before it."""
        seq %= self.mod
        if self.last is None:
            self.last = seq
            self.index = seq if self.index == 0 else self.index + 1
            return 0
        step = (seq - self.last) % self.mod
        self.last = seq
        if step == 0 or step > self.half:  # duplicate or backwards: resync, not a loss
            self.resyncs += 1
            self.index += 1
            return 0
        self.index += step
        self.lost += step - 1
        return step - 1


class ClockUnwrapper:
    """Board microsecond clock to a monotonic count across a 32-bit wrap (71.6 min).

    A 64-bit board clock never wraps and passes through unchanged. A 32-bit clock is unwrapped
    only when the new time follows the previous one by about the sample period modulo 2^32
    (`steps` periods when the sequence numbers say samples were lost in between): one corrupt
    `t_us = 0xFFFFFFFF` once counted as a wrap and shifted that DUT's time by 4,295 s.

    `update()` returns None for a time that does not follow the previous sample: an outlier the
    caller counts as malformed and skips. When the next time follows that outlier instead (the
    board's clock really jumped: a reset, an ODR change), the new timeline is taken as it is
    (no offset change), so a real jump costs one sample, never the rest of the run.
    Until the period is known (first two samples, after `reset_period()`), any forward step of
    less than half the range is accepted, as before.
    """

    WRAP = 1 << 32
    TOLERANCE = 0.5  # of the expected step: board timers are regular, corrupt values are not

    def __init__(self) -> None:
        self.offset = 0
        self.last: int | None = None
        self.period_us: float | None = None
        self.outliers = 0
        self.jumps = 0
        self._candidate: int | None = None
        self._skipped_steps = 0  # periods of the outliers since the last accepted sample

    def reset_period(self) -> None:
        """The sample rate changed: learn the period again from the next step."""
        self.period_us = None

    def _follows(self, step_us: int, steps: int) -> bool:
        if step_us <= 0 or step_us >= self.WRAP // 2:
            return False
        if self.period_us is None:
            return True
        expected = self.period_us * max(1, steps)
        return abs(step_us - expected) <= self.TOLERANCE * expected

    def update(self, t_us: int, steps: int = 1) -> int | None:
        """t_us: the frame's clock; steps: sample periods since the previous frame (1 + lost)."""
        last = self.last
        if last is None or last >= self.WRAP or t_us >= self.WRAP:  # first sample, or a 64-bit clock
            self.last = t_us
            self._candidate = None
            self._skipped_steps = 0
            return t_us + self.offset
        step = (t_us - last) % self.WRAP
        since_last = steps + self._skipped_steps
        if self._follows(step, since_last):
            if t_us < last:
                self.offset += self.WRAP
            self.period_us = step / max(1, since_last)
            self.last = t_us
            self._candidate = None
            self._skipped_steps = 0
            return t_us + self.offset
        cand = self._candidate
        if cand is not None and 0 < t_us - cand < self.WRAP // 2:
            # two samples agree with each other and not with the past: the clock jumped
            self.jumps += 1
            self.period_us = (t_us - cand) / max(1, steps)
            self.last = t_us
            self._candidate = None
            self._skipped_steps = 0
            return t_us + self.offset
        self._candidate = t_us
        self._skipped_steps += steps
        self.outliers += 1
        return None


class StreamTimeline:
    """Is a sample frame on its board's one timeline? (design 3.1: a run is one board's stream)

    A board's seq and clock move together: seq +k, t_us +k sample periods. A frame off that line
    is either garbage that passed the 8-bit checksum (1 in 256 corrupt lines does), a single one
    that the next frames contradict, or the start of another timeline: the board restarted while
    streaming (its seq went back; a reset by power, brown-out or watchdog) or its clock jumped
    while its seq ran on. Only CONFIRM_FRAMES off-line frames that agree with EACH OTHER (seq +1,
    t_us one period on) make a break; anything less is skipped as garbage, never fatal. A forward
    step in time is a gap, not a break, when it is short (MAX_FORWARD_GAP_S) or when the board
    was really silent that long: its frames before and after the step arrived that far apart on the
    station's clock (wall seconds x `speed`, the plant time per wall second: 1 on real hardware). A
    board that stalled and took no samples, counting the frames it sends, is silent for as long as
    its clock moves on; a clock that jumps forward is not.

    Until CONFIRM_FRAMES frames in a row agree, there is no line yet (a stream's first frames, or
    garbage among them) and nothing to break: every frame is fed on.

    `check(seq, t_us)` returns "ok" (feed the frame on), "skip" (off the line, not confirmed),
    "gap" (a confirmed forward gap: feed the frame on) or "reset" / "clock_jump" (the frame
    confirms a new timeline). `restart()` at every START and
    ODR change: the first frames after it define the line.
    """

    CONFIRM_FRAMES = 3
    TOLERANCE = 0.5  # of a sample period per seq step, plus 0.1 % of the step (clock drift)
    MAX_FORWARD_GAP_S = 10.0
    SEQ_MOD = 1 << 32
    T_WRAP = 1 << 32

    def __init__(self, speed: float = 1.0) -> None:
        self.speed = float(speed)
        # the latest confirmed break: (seq, t_us) before it, the first frame after it, the new
        # clock's offset from the old line in us
        self.broke: tuple[tuple[int, int], tuple[int, int], float] | None = None
        self.restart()

    def restart(self) -> None:
        self.last: tuple[int, int] | None = None  # (seq, t_us) of the last frame on the line
        self.last_wall_s: float | None = None  # when it arrived (the station's monotonic clock)
        self.period_us: float | None = None
        self._n_on_line = 0  # frames on the line in a row: under CONFIRM_FRAMES it is not a line yet
        self._cand: list[tuple[int, int]] = []
        self._cand_wall_s: float | None = None  # when the first off-line frame arrived

    def _dt_us(self, t_from: int, t_to: int) -> int:
        if t_from < self.T_WRAP and t_to < self.T_WRAP:  # a 32-bit clock: steps modulo its wrap
            d = (t_to - t_from) % self.T_WRAP
            return d - self.T_WRAP if d >= self.T_WRAP // 2 else d
        return t_to - t_from

    def _on_line(self, a: tuple[int, int], b: tuple[int, int], period_us: float) -> bool:
        k = (b[0] - a[0]) % self.SEQ_MOD
        if k == 0 or k >= self.SEQ_MOD // 2:
            return False
        dt = self._dt_us(a[1], b[1])
        expected = k * period_us
        return abs(dt - expected) <= self.TOLERANCE * period_us + 1e-3 * expected

    def check(self, seq: int, t_us: int, wall_s: float | None = None) -> str:
        """wall_s: when the frame arrived (time.monotonic()); None: unknown (no gap is explained)."""
        frame = (seq % self.SEQ_MOD, t_us)
        last = self.last
        if last is not None and self.period_us is not None and self._on_line(last, frame, self.period_us):
            self.period_us += 0.05 * ((self._dt_us(last[1], frame[1]) / ((frame[0] - last[0]) % self.SEQ_MOD))
                                      - self.period_us)
            self.last, self.last_wall_s, self._cand = frame, wall_s, []
            self._n_on_line += 1
            return "ok"
        if self._n_on_line < self.CONFIRM_FRAMES:
            # No line yet (the stream's first frames, or garbage among them): nothing to break.
            # The line is learned again from the last frame to this one when both move forward.
            forward = last is not None and 0 < (frame[0] - last[0]) % self.SEQ_MOD < self.SEQ_MOD // 2 \
                and self._dt_us(last[1], frame[1]) > 0
            if forward:
                assert last is not None
                self.period_us = self._dt_us(last[1], frame[1]) / ((frame[0] - last[0]) % self.SEQ_MOD)
                self._n_on_line = 2
            else:
                self.period_us, self._n_on_line = None, 1
            self.last, self.last_wall_s, self._cand = frame, wall_s, []
            return "ok"
        return self._candidate(frame, wall_s)

    def _cand_period_us(self) -> float | None:
        """The period the candidates draw (their own: a restarted board may run another ODR)."""
        cand = self._cand
        if len(cand) < 2:
            return None
        return self._dt_us(cand[0][1], cand[1][1]) / ((cand[1][0] - cand[0][0]) % self.SEQ_MOD)

    def _candidate(self, frame: tuple[int, int], wall_s: float | None) -> str:
        cand = self._cand
        agrees = False
        if cand:
            k = (frame[0] - cand[-1][0]) % self.SEQ_MOD
            own = self._cand_period_us()
            if own is None:  # the second candidate: forward in seq and in time
                agrees = 0 < k < self.SEQ_MOD // 2 and self._dt_us(cand[-1][1], frame[1]) > 0
            else:
                agrees = own > 0 and self._on_line(cand[-1], frame, own)
        if agrees:
            cand.append(frame)
        elif len(cand) >= 2 and 0 < (frame[0] - cand[-1][0]) % self.SEQ_MOD < self.SEQ_MOD // 2 \
                and self._dt_us(cand[-1][1], frame[1]) > 0:
            self._cand = cand = [cand[-1], frame]  # the run may start at the last one (garbage before it)
        else:
            self._cand, self._cand_wall_s = [frame], wall_s
            cand = self._cand
        if len(cand) < self.CONFIRM_FRAMES:
            return "skip"
        last, period_us = self.last, self.period_us
        assert last is not None
        k = (cand[0][0] - last[0]) % self.SEQ_MOD
        dt = self._dt_us(last[1], cand[0][1])
        silent_s = None if self._cand_wall_s is None or self.last_wall_s is None else self._cand_wall_s - self.last_wall_s
        gap_max_s = self.MAX_FORWARD_GAP_S + (0.0 if silent_s is None else 1.5 * silent_s * self.speed)
        self.broke = (last, cand[0], dt - (k if k < self.SEQ_MOD // 2 else 0) * (period_us or 0.0))
        own = self._cand_period_us()
        self.restart()
        self.last, self.last_wall_s, self.period_us, self._n_on_line = frame, wall_s, own, len(cand)
        if 0 < k < self.SEQ_MOD // 2 and 0 < dt <= gap_max_s * 1e6:
            return "gap"  # the board took no samples for a while but counted on: the line moves on
        return "reset" if k == 0 or k >= self.SEQ_MOD // 2 else "clock_jump"
