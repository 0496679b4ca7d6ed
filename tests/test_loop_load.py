"""The daemon-side pieces that keep the event loop light at 64 DUTs (benchmarks/web_load.py): the
sample codec's delta coding (db/codec.py) gives the bytes the np.diff definition gives."""

from __future__ import annotations


import numpy as np
import pytest

from db import codec


def reference_shuffle(a: np.ndarray) -> bytes:
    """The stored format's definition: np.diff with a 0 prepended, bytes grouped by significance."""
    d = np.diff(a, prepend=a.dtype.type(0)).astype(a.dtype)
    return d.view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.int16, np.int8])
def test_delta_coding_is_the_stored_format(dtype):
    info = np.iinfo(dtype)
    rng = np.random.default_rng(5)
    cases = [np.array([], dtype=dtype), np.array([7], dtype=dtype),
             np.array([info.max, info.min, -5, 7, info.min, info.max], dtype=dtype),  # wrapping differences
             rng.integers(info.min, info.max, 257, dtype=dtype, endpoint=True),
             np.cumsum(rng.integers(-3, 4, 1000)).astype(dtype)]
    for a in cases:
        assert codec._shuffle(a) == reference_shuffle(a)


def test_encoded_chunks_decode_to_the_same_samples():
    rng = np.random.default_rng(2)
    n = 1500
    q = codec.quantize(np.cumsum(rng.uniform(0.005, 0.02, n)), rng.normal(0, 1, (n, 3)), rng.normal(40, 10, n),
                       rng.integers(0, 2, n), rng.integers(-1, 32, n))
    back = codec.decode(codec.encode(q))
    for f in ("time", "acc", "temp", "lamp", "position"):
        assert np.array_equal(getattr(back, f), getattr(q, f)), f
