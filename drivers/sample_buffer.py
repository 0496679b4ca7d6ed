"""The samples a board link holds until `read_block()` takes them (SerialBoard and CanBoard).

Why a module of its own: both board drivers hold their samples the same way, and the two copies
had begun to differ in small ways. What is the same for every board link lives here: the rows
received and not yet read, the samples lost since the last block (seq gaps, and the oldest rows
dropped when nobody reads for long: MAX_PENDING_SAMPLES), the wake-up of a waiting reader, the
wait for data with the link's own check, the assembly of the rows into one SampleBlock in g and C
with the board's identity, and dropping what is held before a new run. What differs stays in each
driver: how the link turns bytes or frames into rows (parser, seq, clock, timeline) and how a row's
time reads (`Columns`: board microseconds on a serial link, seconds from the sample index on CAN).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import numpy as np

from drivers.base import DriverError, LinkStats
from contracts.types import Identity, SampleBlock

MAX_PENDING_SAMPLES = 2_000_000  # if nobody reads, the oldest samples are dropped (counted lost)

Row = tuple[float, int, int, int, int]  # time (in the link's own unit), ax, ay, az, t: raw counts
# Rows to (time in s, counts (n, 4): ax ay az t), for a non-empty list of rows.
Columns = Callable[[list[Row]], tuple[np.ndarray, np.ndarray]]


class SampleBuffer:
    """Rows a board link received and `read_block()` has not taken yet (see the module doc).

    The driver adds rows as they arrive (`add`, `count_lost`) and calls `flush()` once per burst
    of input: that caps what is held and wakes a reader waiting in `wait()`. Losses are counted in
    the link's `stats` and handed out with the next block.
    """

    def __init__(self, stats: LinkStats, columns: Columns, limit: int = MAX_PENDING_SAMPLES) -> None:
        self.stats = stats
        self.columns = columns
        self.limit = limit
        self._rows: list[Row] = []
        # rows that came in bulk (a driver's fast path: drivers/protocol/sample_lines.py), already
        # as columns (time in s, counts (n, 4)), in arrival order before the rows in _rows
        self._chunks: list[tuple[np.ndarray, np.ndarray]] = []
        self._n_chunked = 0
        self._lost = 0  # samples lost since the last block
        self._fresh = False  # rows added since the last flush()
        self._data = asyncio.Event()

    def __len__(self) -> int:
        return len(self._rows) + self._n_chunked

    def renew(self) -> None:
        """A new wake-up event (the link opens: the reader may wait in another event loop)."""
        self._data = asyncio.Event()

    def add(self, row: Row) -> None:
        self._rows.append(row)
        self._fresh = True

    def add_columns(self, time_s: np.ndarray, counts: np.ndarray) -> None:
        """Many rows at once, already as columns (time in s, raw counts (n, 4)): the bulk path."""
        if self._rows:  # keep the arrival order: the rows before these become a chunk first
            self._chunks.append(self.columns(self._rows))
            self._n_chunked += len(self._rows)
            self._rows = []
        self._chunks.append((time_s, counts))
        self._n_chunked += len(time_s)
        self._fresh = True

    def _columns_all(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Everything held as one pair of columns (and nothing held any more); None when empty."""
        parts = list(self._chunks)
        if self._rows:
            parts.append(self.columns(self._rows))
        self._rows, self._chunks, self._n_chunked = [], [], 0
        if not parts:
            return None
        if len(parts) == 1:
            return parts[0]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def count_lost(self, n: int) -> None:
        """n samples lost on the link (a seq gap): counted, and reported with the next block."""
        self.stats.samples_lost += n
        self._lost += n

    def flush(self) -> None:
        """After a burst of input: when rows came in, drop the oldest beyond the limit (counted
        lost) and wake the reader."""
        if not self._fresh:
            return
        self._fresh = False
        if len(self) > self.limit:
            drop = len(self) - self.limit
            held = self._columns_all()
            assert held is not None
            self._chunks, self._n_chunked = [(held[0][drop:], held[1][drop:])], len(held[0]) - drop
            self.count_lost(drop)
            self.stats.samples_lost_queue += drop
        self._data.set()

    def wake(self) -> None:
        """Wake a waiting reader without rows (the link failed, the stream broke)."""
        self._data.set()

    def discard(self) -> int:
        """Drop the rows held and the losses not yet reported; returns how many rows."""
        n = len(self)
        self._rows, self._chunks, self._n_chunked = [], [], 0
        self._lost = 0
        return n

    async def wait(self, timeout_s: float, check: Callable[[], None],
                   error: Callable[[], DriverError | None]) -> None:
        """With nothing held: `check()` the link (it raises when the link is down or not open),
        then wait up to timeout_s for rows. Still none and the link has failed: its error."""
        if self._rows or self._chunks:
            return
        check()
        self._data.clear()
        try:
            await asyncio.wait_for(self._data.wait(), timeout_s)
        except asyncio.TimeoutError:
            pass
        err = error()
        if not len(self) and err is not None:
            raise err

    def take_block(self, identity: Identity | None) -> SampleBlock:
        """Every row held and the losses since the last block, as one SampleBlock in g and C
        (empty when there are no rows; a board not identified yet reads with Identity's defaults)."""
        held = self._columns_all()
        lost, self._lost = self._lost, 0
        if held is None:
            return SampleBlock(np.empty(0), np.empty((0, 3)), np.empty(0), lost)
        ident = identity or Identity(serial="")
        time_s, counts = held
        return SampleBlock(
            time_s=time_s,
            acc_g=ident.acc_g(counts[:, 0:3]),
            temp_c=ident.temp_c(counts[:, 3]),
            lost_samples=lost,
        )
