"""asyncio helpers shared by the daemon's long-lived tasks (lamp guard, MES outbox)."""

from __future__ import annotations

import asyncio


async def cancel_and_wait(task: asyncio.Task | None, timeout_s: float = 5.0) -> bool:
    """Cancel `task` and wait for it to end, cancelling again while it keeps running. True if it
    ended within timeout_s.

    Why not `task.cancel(); await task`: Python 3.11's asyncio.wait_for can swallow a cancel that
    lands just as its inner wait completes. A watch loop that swallowed one runs on forever, and
    whoever awaits it hangs. CI saw exactly that: the lamp guard's close never returned, so the
    lamp OFF that follows it was never sent."""
    if task is None:
        return True
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not task.done():
        if loop.time() >= end:
            return False
        task.cancel()
        await asyncio.wait({task}, timeout=min(0.2, max(0.0, end - loop.time())))
    if not task.cancelled():
        task.exception()  # retrieved: an error on the way out is not "never retrieved" noise
    return True
