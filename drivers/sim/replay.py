"""Replayed hardware: boards that stream recorded samples, and a plate that reports agreement.

ReplayWorld is the plant of a SimStation (same interface as SimWorld: `advance`, `identity`,
`odr_hz`, `time_s`, and the Modbus plant attributes `lamp_on`, `position`, `chamber_setpoint_c`,
`plate_temp_c`), but its samples are recorded ones: each DUT's stream starts when its board is
first told to START, and from then on the board sends the recorded samples at the pace of the
SimStation clock (`speed`, with the same backpressure as the demo), with the recorded counts,
identity and sample clock. What the daemon commands (lamp, fixture, chamber) cannot change the
data: the relay, fixture and chamber accept the commands (SimModbusServer, as in the demo), and
station/replay/agreement.py compares the plate state the daemon stored beside every replayed
sample with the one recorded beside the same sample.

A recorded stream pauses where the recorded line paused it, so that the daemon meets every sample
in the same state as the recorded one did:
- while a board is stopped (the program step stops it to write its calibration), its record does
  not advance: a board that is not streaming measures nothing, and the recorded stream has no
  samples for that time either;
- a DUT whose recorded board was stopped for programming waits at that point of its record (the
  sample after `restart_after_t`) until the replaying daemon stops it too; its samples after the
  restart are the recorded ones, compensated on the board exactly as recorded (the replay boards
  never compensate again: `compensates = False`);
- `hold(i, index)` keeps DUT i at a recorded index until `release()` (station/replay/director.py:
  an operator prompt is answered at the sample where the recorded operator's answer took effect);
  `hold_at_step_start(i, index)` keeps it just after a recorded step start until the replaying
  daemon has begun that step.
A DUT released from a pause or a hold continues from where it stopped, at the current world time
(its record is re-anchored), so no backlog bursts out. A board whose recorded link was lost
(`unplugged_at_end`) is unplugged when its record has been sent.

ReplayStation is the SimStation that plays a Recording: serial DUTs on ptys with a 64-bit board
clock (so t_us goes over the wire exactly as recorded), CAN DUTs behind the slcan adapter.
"""

from __future__ import annotations

import asyncio
import zlib
from dataclasses import dataclass
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.sim.serial_pty import SimSerialBoard, render_sample_frames
from drivers.sim.slcan_pty import SimCanBoard
from drivers.sim.station_sim import SimStation
from contracts.recording import RecordedDut, Recording
from contracts.types import Identity

START_GRACE_S = 3.0
# A board stopped at most this many sample seconds before its recorded program stop sends the
# recorded samples up to that stop (they were in flight); an earlier stop (a reconnect) does not.
FLUSH_MAX_S = 1200.0
FRAME_CHUNK = 4096  # samples of a record rendered as frames at a time
PRERENDER_MAX_BYTES = 256 << 20  # frames rendered before the replay starts; the rest while it plays


@dataclass
class ReplayPart:
    """The samples of one DUT that fall due in one world advance."""

    time_s: np.ndarray
    acc_counts: np.ndarray
    temp_counts: np.ndarray
    seq: np.ndarray
    start: int  # index in the record of the first sample (a serial board sends its frames rendered ahead)
    flush: bool = False  # sent although the board is stopped: the recorded samples before its stop


@dataclass
class ReplayChunk:
    time_s: np.ndarray  # world sample times of this advance
    parts: list[ReplayPart]

    def __len__(self) -> int:
        return int(self.time_s.shape[0])


class ReplayWorld:
    """The plant of a replay (see module doc). DUT order = SimStation board order."""

    def __init__(self, duts: list[RecordedDut]) -> None:
        if not duts:
            raise ValueError("nothing to replay")
        self.duts = list(duts)
        self._odr_hz = max(float(d.identity.odr_hz) for d in self.duts)
        self._k = 0
        self.lamp_on = False
        self.position = 0
        self.chamber_setpoint_c: float | None = None
        self.requested_odr_hz: list[float] = []
        self._start: list[float | None] = [None] * len(self.duts)  # world time at which DUT i's record starts
        self._delay = _lamp_alignment(self.duts)
        self._next = np.zeros(len(self.duts), dtype=np.int64)  # next recorded sample of DUT i
        self._rel = [d.time_s - d.time_s[0] for d in self.duts]
        self._seq = [d.seq_index() for d in self.duts]
        self._temp_now = np.array([float(d.identity.temp_c(d.temp_counts[:1])[0]) for d in self.duts])
        self.sent = [0] * len(self.duts)
        self._crc = [0] * len(self.duts)
        n = len(self.duts)
        self.streaming_of: Callable[[int], bool] = lambda i: True  # set by ReplayStation: board i streams
        self._stop_at: list[int | None] = [d.restart_index() for d in self.duts]  # recorded program stops
        self._hold_at: list[int | None] = [None] * n  # holds set by the director (prompts)
        self._step_hold_at: list[int | None] = [None] * n  # ... at a recorded step start
        self._held = [False] * n  # DUT i did not advance with the world last time: re-anchor before it does
        # bumped whenever a DUT's next index changes: the director (station/replay/director.py) passes
        # over the DUTs' holds when it has, not at every poll
        self.moves = 0

    # ---- SimWorld interface ------------------------------------------------------------------
    @property
    def n_duts(self) -> int:
        return len(self.duts)

    @property
    def odr_hz(self) -> float:
        return self._odr_hz

    @odr_hz.setter
    def odr_hz(self, hz: float) -> None:  # the recording fixes the rate; a request is noted
        self.requested_odr_hz.append(float(hz))

    @property
    def time_s(self) -> float:
        return self._k / self._odr_hz

    @property
    def plate_temp_c(self) -> float:
        """No plate thermometer is recorded: the median DUT temperature now stands in for it."""
        return float(np.median(self._temp_now))

    @property
    def chamber_air_c(self) -> float:
        return self.plate_temp_c

    def identity(self, i: int) -> Identity:
        return self.duts[i].identity

    def power_cycle(self, i: int, off_s: float = 0.0) -> None:
        """A recorded stream has no physics to restart."""

    @property
    def exhausted(self) -> bool:
        """Every started DUT has sent its whole record (and every DUT has started)."""
        return all(s is not None for s in self._start) and all(self.done(i) for i in range(len(self.duts)))

    def start_dut(self, i: int) -> None:
        """DUT i's board was told to START: its record begins now, or later by its lamp alignment
        (only the first time)."""
        if self._start[i] is None:
            self._start[i] = self.time_s + self._delay[i]

    # ---- pauses and holds (see module doc) ----------------------------------------------------
    def next_index(self, i: int) -> int:
        """Index of the next recorded sample DUT i will send."""
        return int(self._next[i])

    def hold(self, i: int, index: int) -> None:
        """Send DUT i's record up to (not including) `index`, then wait there until release().
        A prompt's hold replaces a step-start hold (the step cannot begin before its answer)."""
        self._hold_at[i] = int(index)
        self._step_hold_at[i] = None

    def hold_at_step_start(self, i: int, index: int | None) -> None:
        """Send DUT i's record up to `index` (a recorded step start) and wait there until this is
        called again with another index or None."""
        self._step_hold_at[i] = None if index is None else int(index)

    def at_hold(self, i: int) -> bool:
        """DUT i has sent its record up to its hold (or has no hold, or has sent it all)."""
        h = self._hold_at[i]
        return h is None or int(self._next[i]) >= h or self.done(i)

    def release(self) -> None:
        self._hold_at = [None] * len(self.duts)

    def done(self, i: int) -> bool:
        """DUT i has sent its whole record."""
        return int(self._next[i]) >= len(self.duts[i])

    def waiting_for_stop(self, i: int) -> bool:
        """DUT i waits at its recorded program stop for the daemon to stop its board."""
        s = self._stop_at[i]
        return s is not None and int(self._next[i]) >= s

    def drop_stop(self, i: int) -> None:
        """Give up DUT i's recorded program stop (the replaying daemon does not stop this board)."""
        self._stop_at[i] = None

    def advance(self, n: int) -> ReplayChunk:
        t0 = self.time_s
        world_t = t0 + np.arange(n) / self._odr_hz
        self._k += n
        t_end = self.time_s
        parts = []
        moved = False
        for i, d in enumerate(self.duts):
            s = self._start[i]
            a = int(self._next[i])
            empty = ReplayPart(d.time_s[:0], d.acc_counts[:0], d.temp_counts[:0], self._seq[i][:0], a)
            if s is None or a >= len(d):
                parts.append(empty)
                continue
            if not self.streaming_of(i):  # stopped: nothing measured, the record waits
                parts.append(self.stopped(i) or empty)
                continue
            if self._held[i]:  # continue from where it stopped, at the current world time
                s = self._start[i] = t0 - float(self._rel[i][a])
                self._held[i] = False
            b = int(np.searchsorted(self._rel[i], t_end - s, side="left"))
            cap = min((x for x in (self._stop_at[i], self._hold_at[i], self._step_hold_at[i]) if x is not None),
                      default=None)
            if cap is not None and b >= cap:
                b = max(a, cap)
                self._held[i] = True
            if b != a:
                self._next[i] = b
                moved = True
            parts.append(ReplayPart(d.time_s[a:b], d.acc_counts[a:b], d.temp_counts[a:b], self._seq[i][a:b], a))
            if b > a:
                self._temp_now[i] = float(d.identity.temp_c(d.temp_counts[b - 1:b])[0])
        self.moves += moved
        return ReplayChunk(world_t, parts)

    def stopped(self, i: int) -> ReplayPart | None:
        """DUT i's board was told to STOP: its record waits here. Stopped before the recorded
        point (the replaying daemon got there sooner), the recorded board's samples up to its
        stop were already on their way when STOP took effect: they are returned (flush) to go out
        at once, ahead of the STOP's reply, so the daemon has them before it writes, as the line
        had (ReplayStation calls this from the board's STOP, not at the next plant advance, which
        a busy daemon can hold back)."""
        d, a, stop = self.duts[i], int(self._next[i]), self._stop_at[i]
        if self._start[i] is None or a >= len(d):
            return None
        self._held[i] = True
        self._stop_at[i] = None  # the recorded stop happened (here or a little earlier)
        if stop is not None and a < stop and float(self._rel[i][stop] - self._rel[i][a]) <= FLUSH_MAX_S:
            self._next[i] = stop
            self.moves += 1
            return ReplayPart(d.time_s[a:stop], d.acc_counts[a:stop], d.temp_counts[a:stop], self._seq[i][a:stop],
                              a, flush=True)
        return None

    def note_sent(self, i: int, part: ReplayPart) -> None:
        """What board i actually put on the wire (a board not streaming sends nothing)."""
        if len(part.time_s):
            self.sent[i] += len(part.time_s)
            self._crc[i] = zlib.crc32(_sample_bytes(part.time_s, part.acc_counts, part.temp_counts), self._crc[i])

    def sent_digest(self, i: int) -> tuple[int, int]:
        return self.sent[i], self._crc[i]

    def seq(self, i: int) -> np.ndarray:
        """The frame sequence number of each of DUT i's recorded samples (RecordedDut.seq_index)."""
        return self._seq[i]


class RenderedRecord:
    """One serial DUT's record as the design-3.1 frames its board sends, rendered in chunks of
    FRAME_CHUNK samples (serial_pty.render_sample_frames: vectorised, byte for byte the board's
    own feed()). A record is sent forward only, in contiguous pieces (ReplayWorld), so a piece is
    a slice of one or two rendered chunks and a chunk behind the piece is dropped: sending costs no
    Python work per sample, and the rendered frames held stay bounded however long the record."""

    def __init__(self, d: RecordedDut, seq: np.ndarray) -> None:
        self._d = d
        self._seq = np.asarray(seq, dtype=np.int64) & 0xFFFFFFFF
        self._chunks: dict[int, tuple[bytes, np.ndarray]] = {}

    def _chunk(self, c: int) -> tuple[bytes, np.ndarray]:
        got = self._chunks.get(c)
        if got is None:
            a, b = c * FRAME_CHUNK, min((c + 1) * FRAME_CHUNK, len(self._d))
            t_us = np.round(np.asarray(self._d.time_s[a:b], dtype=np.float64) * 1e6).astype(np.int64)
            got = self._chunks[c] = render_sample_frames(self._seq[a:b], t_us, self._d.acc_counts[a:b],
                                                         self._d.temp_counts[a:b])
        return got

    def prerender(self, budget_bytes: int) -> int:
        """Render chunks from the record's start while they fit in budget_bytes; the bytes used."""
        used = 0
        for c in range(-(-len(self._d) // FRAME_CHUNK)):
            if used >= budget_bytes:
                break
            used += len(self._chunk(c)[0])
        return used

    def frames(self, a: int, b: int) -> bytes:
        """The frames of samples a..b-1 (b > a)."""
        first, last = a // FRAME_CHUNK, (b - 1) // FRAME_CHUNK
        for c in [c for c in self._chunks if c < first]:
            del self._chunks[c]
        pieces = []
        for c in range(first, last + 1):
            data, off = self._chunk(c)
            base = c * FRAME_CHUNK
            pieces.append(data[off[max(a, base) - base]:off[min(b, base + FRAME_CHUNK) - base]])
        return pieces[0] if len(pieces) == 1 else b"".join(pieces)


# How the recorded board answered the station's calibration write (db program record's error_kind)
# -> the fault its replay twin is armed with, so that it answers the same way (board_nvm.CalFirmware).
_WRITE_FAULTS: dict[str, Callable[[Any], None]] = {
    "refused": lambda cal: cal.refuse_writes(1_000_000),
    "no_reply": lambda cal: cal.drop_replies(1_000_000),
    "crc_mismatch": lambda cal: cal.flip_next_write(1_000_000),
    "readback_mismatch": lambda cal: cal.corrupt_readback_crc(1_000_000),
}


def _as_recorded(board: Any, d: RecordedDut) -> Any:
    """A replay board: its samples go out as recorded (never compensated again), and its
    calibration write fails the way the recorded one did; otherwise it takes the daemon's writes
    and answers read-backs from what it was given."""
    board.compensates = False
    arm = _WRITE_FAULTS.get(d.program_error_kind or "")
    if arm is not None:
        arm(board.cal)
    return board


def _lamp_alignment(duts: list[RecordedDut]) -> list[float]:
    """Sample seconds each record starts after the earliest one, so that every DUT reaches its
    first lamp switch-on at the same moment, as on the recorded plate. Records start at each
    board's first sample after its START, and those are seconds of wall time apart, i.e. many
    sample seconds in compressed time; the lamp switched on for all DUTs at one instant, so it is
    the common clock. Without a lamp column (or a switch-on in every record): all start together."""
    lead = []
    for d in duts:
        if d.lamp is None:
            return [0.0] * len(duts)
        on = np.flatnonzero((d.lamp[1:] > 0) & (d.lamp[:-1] == 0))
        if not len(on):
            return [0.0] * len(duts)
        lead.append(float(d.time_s[on[0] + 1] - d.time_s[0]))
    c = max(lead)
    return [c - x for x in lead]


def _sample_bytes(time_s: np.ndarray, acc_counts: np.ndarray, temp_counts: np.ndarray) -> bytes:
    t_us = np.rint(np.asarray(time_s, dtype=np.float64) * 1e6).astype(np.int64)
    rows = np.column_stack([t_us, np.asarray(acc_counts, dtype=np.int64), np.asarray(temp_counts, dtype=np.int64)])
    return np.ascontiguousarray(rows, dtype="<i8").tobytes()


def recorded_digest(d: RecordedDut) -> tuple[int, int]:
    """(samples, crc32) of a whole record, to compare with ReplayWorld.sent_digest."""
    return len(d), zlib.crc32(_sample_bytes(d.time_s, d.acc_counts, d.temp_counts))


class ReplayStation(SimStation):
    """A SimStation whose boards play a Recording (serial DUTs first, then CAN, in record order)."""

    def __init__(self, recording: Recording, speed: float = 60.0, *, can_interface: str = "slcan",
                 tick_s: float = 0.05, move_time_s: float = 4.0) -> None:
        serial = [d for d in recording.duts if d.link != "can"]
        can = [d for d in recording.duts if d.link == "can"]
        self.recording = recording
        self.ordered: list[RecordedDut] = serial + can
        world = ReplayWorld(self.ordered)
        world.streaming_of = self._streams
        # each serial DUT's frames, rendered now (as far as PRERENDER_MAX_BYTES goes) rather than
        # sample by sample while the daemon is reading: the replay's boards should cost the
        # daemon's machine as little as the real ones, which cost it nothing
        self._rendered = {i: RenderedRecord(d, world.seq(i)) for i, d in enumerate(self.ordered) if d.link != "can"}
        budget = PRERENDER_MAX_BYTES
        for r in self._rendered.values():
            budget -= r.prerender(budget)
        self._first_start: float | None = None
        self._unplugged: set[int] = set()
        super().__init__(n_serial=len(serial), n_can=len(can), speed=speed, world=world,
                         can_interface=can_interface, tick_s=tick_s, move_time_s=move_time_s)

    def _streams(self, i: int) -> bool:
        b = self.board(i)
        return bool(b.streaming) and not getattr(b, "muted", False)

    def _make_serial_board(self, i: int) -> SimSerialBoard:
        board = SimSerialBoard(self.world.identity(i), clock_bits=None)  # 64-bit clock: t_us as recorded
        board.on_stop = lambda: self._on_stop(i)
        return _as_recorded(board, self.ordered[i])

    def _make_can_board(self, j: int, node: int) -> SimCanBoard:
        i = self.n_serial + j
        board = super()._make_can_board(j, node)
        board.on_stop = lambda: self._on_stop(i)
        return _as_recorded(board, self.ordered[i])

    def _on_stop(self, i: int) -> None:
        part = self.world.stopped(i)  # type: ignore[attr-defined]
        if part is not None:
            self._send(i, part)

    def _deliver(self, chunk: Any) -> None:
        world: ReplayWorld = self.world  # type: ignore[assignment]
        streaming = [self.board(i).streaming for i in range(world.n_duts)]
        now = asyncio.get_running_loop().time()
        if any(streaming) and self._first_start is None:
            self._first_start = now
        # the boards get START one after the other: records start together once all stream (or a
        # board is late by more than START_GRACE_S wall seconds: it starts on its own then)
        if self._first_start is not None and (all(streaming) or now - self._first_start > START_GRACE_S):
            for i, on in enumerate(streaming):
                if on:
                    world.start_dut(i)
        for i, part in enumerate(chunk.parts):
            self._send(i, part)
        for i, d in enumerate(self.ordered):
            if d.unplugged_at_end and world.done(i) and i not in self._unplugged:
                self._unplugged.add(i)  # as recorded: the link was lost where the record ends
                self.board(i).disconnect()
        for cb in self._listeners:
            cb(chunk)

    def _send(self, i: int, part: ReplayPart) -> None:
        """Board i puts a part of its record on the wire (a flush even though it is stopped)."""
        if not len(part.time_s):
            return
        board = self.board(i)
        if getattr(board, "muted", False) or not (board.streaming or part.flush):
            return
        was_streaming, board.streaming = board.streaming, True  # a flush goes out past the STOP
        rendered = self._rendered.get(i)
        n = len(part.time_s)
        if rendered is not None and isinstance(board, SimSerialBoard) and board.sends_counts_as_given():
            # the recorded seq is in the rendered frames: a gap skips its numbers as below
            board.send_rendered(rendered.frames(part.start, part.start + n), n, float(part.time_s[-1]),
                                int(part.seq[-1]) + 1)
        else:
            mask = 0xFF if isinstance(board, SimCanBoard) else 0xFFFFFFFF
            # contiguous pieces between recorded gaps: the board skips the lost sequence numbers
            cuts = np.flatnonzero(np.diff(part.seq) != 1) + 1
            for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(part.seq)]):
                board.seq = int(part.seq[a]) & mask
                board.feed(part.time_s[a:b], part.acc_counts[a:b], part.temp_counts[a:b])
        board.streaming = was_streaming
        self.world.note_sent(i, part)  # type: ignore[attr-defined]

    def replay_slot_names(self) -> list[str]:
        return [d.slot for d in self.ordered]

    def pace_by(self, taken: Callable[[], dict[str, int]], max_lead_s: float) -> None:
        """Hold the recorded plant while a streaming DUT's samples sent run more than max_lead_s
        of sample time ahead of what the daemon has taken in (`taken()`: samples by slot). A live
        plant cannot wait for a slow daemon, a recording can: the daemon then sees the data at the
        pace it would at x1, whatever the machine's load or the number of DUTs."""
        world: ReplayWorld = self.world  # type: ignore[assignment]

        def pace() -> bool:
            try:
                got = taken()
            except KeyError:  # the batch is gone (ended): nothing to wait for
                return False
            for i, d in enumerate(self.ordered):
                n = got.get(d.slot)
                if n is not None and self.board(i).streaming and world.sent[i] - n > max_lead_s * d.identity.odr_hz:
                    return True
            return False

        self.pace = pace
