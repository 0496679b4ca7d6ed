"""slcan (Lawicel) receive lines, parsed in bulk (pure: bytes in, frames out).

python-can's slcan reader takes the adapter's bytes one `Serial.read(1)` call at a time, which was
~40 % of the daemon's CPU with 16 CAN boards. The CAN bus reader (drivers/can_board.py)
reads whatever the port holds in one call and splits it here. Only what the station uses is
decoded: standard data frames `tIIILDD..\\r`; extended/remote/FD frames and the adapter's acks
(`\\r`, `z\\r`, `Z\\r`) and errors (BEL) are skipped; a line that is not a well-formed frame is
counted as garbled (line noise), never raised.

`split_frame_runs` is the bulk form (the station's reader): the clean common case, a run of
standard 8-byte data frames, is decoded with numpy into one `FrameRun`; every other line goes
through `split_frames`, which stays the one definition of what a line means.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from functools import cached_property

import can
import numpy as np

CR = 0x0D
BEL = 0x07
_HEX = frozenset(b"0123456789abcdefABCDEF")
MAX_LINE = 64  # longer than any classic frame line: garbage without a CR


def is_line_noise(exc: BaseException) -> bool:
    """A garbled line from the adapter, not a failed link (python-can's own slcan reader).

    python-can's slcan parser raises on a corrupt line: ValueError/IndexError from int() or
    bytes.fromhex, or CanOperationError wrapping the UnicodeDecodeError of a non-ASCII byte.
    One such line once failed the whole bus (every CAN board of the plate); OSError and pyserial's
    SerialException (an OSError) still mean the port is gone."""
    if isinstance(exc, (ValueError, IndexError)):
        return True
    return isinstance(exc, can.CanOperationError) and isinstance(exc.__cause__, (ValueError, IndexError))


def drop_partial_line(bus: object) -> None:
    """python-can's slcan keeps an undecodable line in its buffer (the decode fails before the
    clear), so every later line would fail too: drop it."""
    buf = getattr(bus, "_buffer", None)
    if isinstance(buf, bytearray):
        buf.clear()


def split_frames(buf: bytearray) -> tuple[list[tuple[int, bytes]], int]:
    """Consume the complete lines of `buf` (in place; a partial last line stays for the next read).

    Returns ([(arbitration_id, data), ...] of standard data frames, number of garbled lines)."""
    frames: list[tuple[int, bytes]] = []
    garbled = 0
    start = 0
    n = len(buf)
    while True:
        cr = buf.find(b"\r", start)
        bel = buf.find(b"\x07", start)
        end = cr if bel < 0 or (0 <= cr < bel) else bel
        if end < 0:
            break
        line = bytes(buf[start:end])
        start = end + 1
        if not line:
            continue  # an ack ("\r") or the adapter's error bell alone
        if buf[end] == BEL:
            garbled += 1  # a frame is never ended by the bell: whatever preceded it is noise
            continue
        kind = line[0]
        if kind == 0x74:  # 't': standard data frame
            frame = _standard(line)
            if frame is None:
                garbled += 1
            else:
                frames.append(frame)
        elif kind in (0x54, 0x72, 0x52, 0x64, 0x44, 0x62, 0x42, 0x7A, 0x5A, 0x46, 0x56, 0x76, 0x4E):
            continue  # T r R d D b B (not used here), z/Z acks, F status, V/v version, N serial
        else:
            garbled += 1
    rest = n - start
    if rest > MAX_LINE:  # no CR for longer than any frame: noise; keep the tail only
        garbled += 1
        start = n - MAX_LINE
    del buf[:start]
    return frames, garbled


def _standard(line: bytes) -> tuple[int, bytes] | None:
    if len(line) < 5 or not all(c in _HEX for c in line[1:5]):
        return None
    dlc = line[4] - 0x30
    if not 0 <= dlc <= 8 or len(line) not in (5 + 2 * dlc, 9 + 2 * dlc):  # + 4 hex digits: adapter timestamp
        return None
    payload = line[5:5 + 2 * dlc]
    if not all(c in _HEX for c in payload):
        return None
    return int(line[1:4], 16), bytes.fromhex(payload.decode("ascii"))


# ---- bulk --------------------------------------------------------------------------------

_CLEAN_LEN = 21  # 't' + 3 hex id + '8' + 16 hex data (no adapter timestamp)
_HEXVAL = np.full(256, -1, dtype=np.int16)
for _i, _c in enumerate(b"0123456789abcdef"):
    _HEXVAL[_c] = _i
    _HEXVAL[bytes([_c]).upper()[0]] = _i
_HEX_COLS = np.array([1, 2, 3, *range(5, _CLEAN_LEN)])  # the hex digits of a clean line


@dataclass(frozen=True)
class FrameRun:
    """Consecutive standard 8-byte data frames, in order: ids (n,) int64, data (n, 8) uint8.

    The same frames `split_frames` would return as (id, bytes) tuples, without a Python object
    per frame (the reader thread and the loop then handle them a run at a time)."""

    ids: np.ndarray
    data: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def frame(self, k: int) -> tuple[int, bytes]:
        """Frame k as `split_frames` gives it."""
        return self.frames[k]

    @cached_property
    def frames(self) -> list[tuple[int, bytes]]:
        """Every frame as `split_frames` gives it (made once: numpy's per-element access is slow)."""
        raw = self.data.tobytes()
        return [(i, raw[8 * k:8 * k + 8]) for k, i in enumerate(self.ids.tolist())]


def pop_merged(inbox: deque[tuple[int, bytes] | FrameRun]) -> tuple[int, bytes] | FrameRun:
    """The next item of a reader's inbox (not empty; only the caller pops), consecutive FrameRuns
    joined into one. Why: the loop's cost is per run: several reads' runs cost it one."""
    item = inbox.popleft()
    if not isinstance(item, FrameRun) or not inbox or not isinstance(inbox[0], FrameRun):
        return item
    runs = [item]
    while inbox and isinstance(inbox[0], FrameRun):
        nxt = inbox.popleft()
        assert isinstance(nxt, FrameRun)
        runs.append(nxt)
    return FrameRun(np.concatenate([r.ids for r in runs]), np.concatenate([r.data for r in runs]))


def split_frame_runs(buf: bytearray) -> tuple[list[tuple[int, bytes] | FrameRun], int]:
    """`split_frames` in bulk: the same frames in the same order and the same garbled count, and
    `buf` left the same; runs of clean 8-byte standard frames come as one `FrameRun` each."""
    raw = np.frombuffer(bytes(buf), dtype=np.uint8)
    term = np.flatnonzero((raw == CR) | (raw == BEL))
    out: list[tuple[int, bytes] | FrameRun] = []
    garbled = 0
    if len(term):
        starts = np.empty(len(term), dtype=np.int64)
        starts[0] = 0
        starts[1:] = term[:-1] + 1
        clean = (term - starts == _CLEAN_LEN) & (raw[term] == CR)
        cand = np.flatnonzero(clean)
        if len(cand):
            rows = raw[starts[cand][:, None] + np.arange(_CLEAN_LEN)]
            hexv = _HEXVAL[rows[:, _HEX_COLS]]
            clean[cand] = (rows[:, 0] == 0x74) & (rows[:, 4] == 0x38) & (hexv >= 0).all(axis=1)
        # stretches of lines alike (clean or not), in order
        edges = np.flatnonzero(np.diff(clean.astype(np.int8))) + 1
        bounds = [0, *edges.tolist(), len(term)]
        for a, b in zip(bounds[:-1], bounds[1:]):
            if clean[a]:
                rows = raw[starts[a:b][:, None] + np.arange(_CLEAN_LEN)]
                hexv = _HEXVAL[rows[:, _HEX_COLS]].astype(np.int64)
                ids = hexv[:, 0] * 256 + hexv[:, 1] * 16 + hexv[:, 2]
                data = (hexv[:, 3::2] * 16 + hexv[:, 4::2]).astype(np.uint8)
                out.append(FrameRun(ids, data))
            else:
                frames, bad = split_frames(bytearray(raw[int(starts[a]):int(term[b - 1]) + 1].tobytes()))
                out.extend(frames)
                garbled += bad
        del buf[:int(term[-1]) + 1]
    frames, bad = split_frames(buf)  # the partial last line: kept, or cut when too long
    assert not frames
    return out, garbled + bad
