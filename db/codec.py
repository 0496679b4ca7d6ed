"""Compressed sample blocks for the sample_chunk table.

Every column is quantized to integers at the log file's stored precision (contracts/logfile.py:
1e-6 s, 1e-7 g, 1e-4 C), delta coded, byte-shuffled and zlib compressed. Integers make the round
trip exact: decoding gives q / 10**d, the double nearest to the decimal the CSV would print, so a
run exported from the database is the same CSV as the samples written straight to a log.
Quantized sensors (LIS3DSH 0.06 mg and 1 C steps) leave small, repetitive deltas, which zlib
shrinks to a couple of bytes per sample.

Layout: magic b"SC1", uint8 flags, uint32 n, then zlib(columns), each column delta coded
(int64 for time, int32 for acc x/y/z and temperature, int8 lamp, int16 position) and shuffled so
that the bytes of equal significance sit together.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from contracts.logfile import ACC_DECIMALS, TEMP_DECIMALS, TIME_DECIMALS

MAGIC = b"SC1"
_HEADER = struct.Struct("<3sBI")
TIME_SCALE = 10**TIME_DECIMALS
ACC_SCALE = 10**ACC_DECIMALS
TEMP_SCALE = 10**TEMP_DECIMALS
_COLUMNS: tuple[tuple[str, type], ...] = (
    ("time", np.int64),
    ("ax", np.int32),
    ("ay", np.int32),
    ("az", np.int32),
    ("temp", np.int32),
    ("lamp", np.int8),
    ("position", np.int16),
)


@dataclass
class Samples:
    """Decoded columns of one or more chunks; position -1 where unknown, lamp 0/1."""

    time_s: np.ndarray
    acc_g: np.ndarray
    temp_c: np.ndarray
    lamp: np.ndarray
    position: np.ndarray

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    @staticmethod
    def concat(parts: list["Samples"]) -> "Samples":
        if not parts:
            return Samples(np.empty(0), np.empty((0, 3)), np.empty(0), np.empty(0, np.int8), np.empty(0, np.int16))
        return Samples(
            np.concatenate([p.time_s for p in parts]),
            np.concatenate([p.acc_g for p in parts]),
            np.concatenate([p.temp_c for p in parts]),
            np.concatenate([p.lamp for p in parts]),
            np.concatenate([p.position for p in parts]),
        )


@dataclass
class Quantized:
    """Integer columns at the stored precision (what a chunk holds)."""

    time: np.ndarray  # int64, microseconds
    acc: np.ndarray  # int32 (n, 3), 1e-7 g
    temp: np.ndarray  # int32, 1e-4 C
    lamp: np.ndarray  # int8
    position: np.ndarray  # int16

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @staticmethod
    def concat(parts: list["Quantized"]) -> "Quantized":
        return Quantized(
            np.concatenate([p.time for p in parts]),
            np.concatenate([p.acc for p in parts]),
            np.concatenate([p.temp for p in parts]),
            np.concatenate([p.lamp for p in parts]),
            np.concatenate([p.position for p in parts]),
        )

    def samples(self) -> Samples:
        return Samples(
            self.time / TIME_SCALE,
            self.acc / ACC_SCALE,
            self.temp / TEMP_SCALE,
            self.lamp.copy(),
            self.position.copy(),
        )


def quantize(
    time_s: np.ndarray,
    acc_g: np.ndarray,
    temp_c: np.ndarray,
    lamp: np.ndarray | int | bool = 0,
    position: np.ndarray | int | None = None,
) -> Quantized:
    """Round to the stored precision (round half to even, like printf on all but exact ties)."""
    time_s = np.asarray(time_s, dtype=np.float64).reshape(-1)
    n = time_s.shape[0]
    acc_g = np.asarray(acc_g, dtype=np.float64).reshape(n, 3)
    temp_c = np.asarray(temp_c, dtype=np.float64).reshape(n)
    if not (np.isfinite(acc_g).all() and np.isfinite(temp_c).all() and np.isfinite(time_s).all()):
        raise ValueError("samples must be finite to be stored")
    acc_q = np.rint(acc_g * ACC_SCALE)
    if np.abs(acc_q).max(initial=0) >= 2**31:
        raise ValueError("acceleration beyond +-214 g cannot be stored")
    lamp_a = np.broadcast_to(np.asarray(lamp, dtype=np.int8), (n,)).copy()
    pos = -1 if position is None else position
    pos_a = np.broadcast_to(np.asarray(pos, dtype=np.int16), (n,)).copy()
    return Quantized(
        np.rint(time_s * TIME_SCALE).astype(np.int64),
        acc_q.astype(np.int32),
        np.rint(temp_c * TEMP_SCALE).astype(np.int32),
        lamp_a,
        pos_a,
    )


def _shuffle(a: np.ndarray) -> bytes:
    """Delta code (first value as is, then the wrapping difference to the one before), then group
    bytes by significance (what blosc/HDF5 call 'shuffle'). The subtraction in place of np.diff
    gives the same integers at a fraction of the cost: the database writer encodes every run's
    new samples several times a second, on the thread that shares the daemon's GIL."""
    d = np.empty_like(a)
    if len(a):
        d[0] = a[0]
        np.subtract(a[1:], a[:-1], out=d[1:])
    return d.view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()


def _unshuffle(buf: bytes, dtype: type, n: int) -> np.ndarray:
    item = np.dtype(dtype).itemsize
    b = np.frombuffer(buf, dtype=np.uint8).reshape(item, n).T.copy()
    d = b.view(dtype).reshape(n)
    return np.cumsum(d, dtype=dtype)


def encode(q: Quantized, level: int = 6) -> bytes:
    n = len(q)
    cols = {
        "time": q.time,
        "ax": q.acc[:, 0],
        "ay": q.acc[:, 1],
        "az": q.acc[:, 2],
        "temp": q.temp,
        "lamp": q.lamp,
        "position": q.position,
    }
    raw = b"".join(_shuffle(np.ascontiguousarray(cols[name], dtype=dt)) for name, dt in _COLUMNS)
    return _HEADER.pack(MAGIC, 0, n) + zlib.compress(raw, level)


def decode(data: bytes) -> Quantized:
    magic, _flags, n = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ValueError(f"not a sample chunk (magic {magic!r})")
    raw = zlib.decompress(data[_HEADER.size :])
    out = {}
    off = 0
    for name, dt in _COLUMNS:
        size = np.dtype(dt).itemsize * n
        out[name] = _unshuffle(raw[off : off + size], dt, n)
        off += size
    if off != len(raw):
        raise ValueError("sample chunk has trailing bytes")
    return Quantized(
        out["time"],
        np.column_stack([out["ax"], out["ay"], out["az"]]).astype(np.int32),
        out["temp"],
        out["lamp"],
        out["position"],
    )


__all__ = ["Samples", "Quantized", "quantize", "encode", "decode"]
