"""numpy's own reductions over arrays that are never built whole: bounded memory, the same bits.

Why a module of its own (issue 40): the offline analyses of a record (offline_fit, residual,
part_noise, the SFEM's static detection) used to build per-sample temporaries of the whole record
(differences, residuals, index lists, their concatenations): ten of them are 2-3 GB on a 200 MB log.
Computing them a chunk at a time bounds the memory, and the results must stay what they were
to the last bit, so that a calibration's numbers do not move with the log's length. Each helper
here repeats the order of operations numpy itself uses:

- `pairwise_sum`: np.add.reduce of a contiguous float64 vector sums pairwise, splitting n at
  n/2 rounded down to a multiple of 8 until a piece is small; splitting the same way and letting
  numpy sum the leaves gives its exact result (np.mean = that sum / n);
- `rows_sum`: a reduction over axis 0 of a C-ordered (n, k) array adds the rows one after another,
  so a running sum carried from chunk to chunk, added in the same order, is exact;
- `median_into`: np.median partitions a copy; partitioning a buffer we own gives the same values.

tests/test_long_logs.py holds each of them to np.sum / np.mean / np.median on random data.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterator, Sequence

import numpy as np

PIECE = 1 << 16  # elements a helper holds at once (a leaf of the pairwise sum, a chunk of a pass)
_UNROLL = 8  # numpy's pairwise sum splits at multiples of its unroll factor


def pairwise_sum(piece: Callable[[int, int], np.ndarray], n: int) -> float:
    """np.add.reduce of a contiguous float64 vector of n elements, exactly, never holding more than
    PIECE of them: piece(a, b) returns elements [a, b)."""
    if n <= PIECE:
        return float(np.add.reduce(piece(0, n))) if n else 0.0

    def node(a: int, m: int) -> float:
        if m <= PIECE:
            return float(np.add.reduce(piece(a, a + m)))
        h = m // 2
        h -= h % _UNROLL
        return node(a, h) + node(a + h, m - h)

    return node(0, n)


def rows_sum(chunks: Iterator[np.ndarray], width: int) -> np.ndarray:
    """np.add.reduce(X, axis=0) of the (n, width) array X that `chunks` yields in row order,
    exactly (a sequential sum over rows, carried between chunks). Zeros when X has no rows."""
    carry: np.ndarray | None = None
    for c in chunks:
        if c.shape[0] == 0:
            continue
        carry = np.add.reduce(c if carry is None else np.vstack((carry[None, :], c)), axis=0)
    return np.zeros(width) if carry is None else carry


def rows_mean_std(rows: Callable[[], Iterator[np.ndarray]], n: int, ddof: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(X.mean(axis=0), X.std(axis=0, ddof=ddof)) of the (n, k) array X whose rows `rows()`
    yields in order (called twice: the mean, then the squared deviations), as numpy computes them."""
    mean = rows_sum(rows(), 3) / n

    def sq() -> Iterator[np.ndarray]:
        for c in rows():
            d = c - mean
            yield np.multiply(d, d, out=d)

    return mean, np.sqrt(rows_sum(sq(), 3) / max(n - ddof, 0))


def median_into(buf: np.ndarray) -> float:
    """np.median(buf) without its copy: buf (which we own) is reordered."""
    return float(np.median(buf, overwrite_input=True))


class Spans:
    """The concatenation over index spans [(s, e), ...] of what each contributes, never built:
    f(s, e, lo, hi) gives elements [lo, hi) of span (s, e)'s part (length(s, e) elements: e - s
    for the samples themselves, e - s - 1 for their differences); `piece(a, b)` gives elements
    [a, b) of the whole (for pairwise_sum), `fill(out)` writes it into a buffer."""

    def __init__(self, spans: Sequence[tuple[int, int]], f: Callable[[int, int, int, int], np.ndarray],
                 length: Callable[[int, int], int] = lambda s, e: e - s) -> None:
        self.spans = [(s, e) for s, e in spans if length(s, e) > 0]
        self.f = f
        self.offsets = [0]
        for s, e in self.spans:
            self.offsets.append(self.offsets[-1] + length(s, e))

    @property
    def n(self) -> int:
        return self.offsets[-1]

    def piece(self, a: int, b: int) -> np.ndarray:
        parts = []
        k = bisect.bisect_right(self.offsets, a) - 1
        while a < b:
            s, e = self.spans[k]
            lo, hi = a - self.offsets[k], min(b, self.offsets[k + 1]) - self.offsets[k]
            parts.append(self.f(s, e, lo, hi))
            a = self.offsets[k] + hi
            k += 1
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def chunks(self) -> Iterator[np.ndarray]:
        for a in range(0, self.n, PIECE):
            yield self.piece(a, min(a + PIECE, self.n))

    def fill(self, out: np.ndarray) -> np.ndarray:
        for a in range(0, self.n, PIECE):
            b = min(a + PIECE, self.n)
            out[a:b] = self.piece(a, b)
        return out


def diffs(x: np.ndarray, spans: Sequence[tuple[int, int]]) -> Spans:
    """np.concatenate([np.diff(x[s:e], axis=0) for s, e in spans]), never built."""
    return Spans(spans, lambda s, e, lo, hi: x[s + lo + 1:s + hi + 1] - x[s + lo:s + hi], lambda s, e: e - s - 1)


def values(x: np.ndarray, spans: Sequence[tuple[int, int]]) -> Spans:
    """np.concatenate([x[s:e] for s, e in spans]), never built."""
    return Spans(spans, lambda s, e, lo, hi: x[s + lo:s + hi])


def pieces(spans: Sequence[tuple[int, int]], size: int = PIECE) -> Iterator[tuple[int, int]]:
    """The spans cut into pieces of at most `size` samples, in order."""
    for s, e in spans:
        for a in range(s, e, size):
            yield a, min(a + size, e)


def split_bounds(s: int, e: int, parts: int) -> list[tuple[int, int]]:
    """np.array_split(np.arange(s, e), parts) as (start, end) pairs: the first (e - s) % parts
    pieces one longer."""
    each, extra = divmod(e - s, parts)
    out, a = [], s
    for k in range(parts):
        b = a + each + (1 if k < extra else 0)
        out.append((a, b))
        a = b
    return out


def keep_rows(keep: np.ndarray, *arrays: np.ndarray) -> list[np.ndarray]:
    """The rows where `keep` holds moved to the front of each array, in order, a piece at a time
    (no copy of an array); returns the arrays cut to them (views). The arrays are overwritten."""
    n = keep.shape[0]
    if keep.all():
        return [x[:n] for x in arrays]
    w = 0
    for a in range(0, n, PIECE):
        k = keep[a:a + PIECE]
        m = int(np.count_nonzero(k))
        for x in arrays:
            x[w:w + m] = x[a:a + PIECE][k]  # the right side is a copy of this piece: w <= a, never read after written
        w += m
    return [x[:w] for x in arrays]


def median_step_s(time_s: np.ndarray) -> float:
    """np.median(np.diff(time_s)) with one buffer (no copy of it for the median)."""
    return median_into(np.diff(np.asarray(time_s, dtype=np.float64).reshape(-1)))


__all__ = ["PIECE", "pairwise_sum", "rows_sum", "rows_mean_std", "median_into", "Spans", "diffs", "values", "pieces", "split_bounds",
           "keep_rows", "median_step_s"]
