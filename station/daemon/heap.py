"""Keep Python's cyclic garbage collector from stalling the daemon's event loop.

A full collection (generation 2) walks every tracked object with the GIL held. Right after start
the daemon holds ~250,000 of them, nearly all made by the imports (FastAPI, pydantic, SQLAlchemy,
numpy, scipy) and never garbage; with 64 DUTs streaming a full collection comes every 15-30 s and
takes 150-200 ms, during which no sample is ingested and no request answered: it alone set the p99
of GET /api/batches/{id} (benchmarks/web_load.py: p99 37 ms with it, 10 ms with the start-up heap
frozen). `freeze_startup_heap()` moves what is alive once the daemon has started into the
permanent generation, so full collections walk only what the batches made since. Frozen objects
are still freed by reference counting; only a reference cycle among them would never be freed,
hence the collection just before.
"""

from __future__ import annotations

import gc


def freeze_startup_heap() -> int:
    """Collect, then freeze what is alive (call once, after the daemon started); returns how many
    objects were frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


__all__ = ["freeze_startup_heap"]
