"""Database reads of the routes, never stuck behind a database that does not answer.

Why: a route that reads the database runs in the thread pool; against a hung server (a stopped
PostgreSQL, a lost network) every such request used to wait for ever, and 40 of them used up the
pool and froze the whole API, the operator's Abort included. Now:
- while the station's database probe (station/daemon/storage.py DbProbe) says the database does
  not answer, a read is refused at once with 503 and the probe's words ("database not answering
  since 12 s"): no thread is taken;
- a read that started before the probe noticed answers 503 after DB_READ_TIMEOUT_S (its thread
  ends when the database does);
- a driver's connection error is a 503 with its first line, not a 500.
"""

from __future__ import annotations

import asyncio
from typing import Callable, TypeVar

from fastapi import HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.exc import OperationalError

from contracts.types import StorageUnavailable

T = TypeVar("T")
DB_READ_TIMEOUT_S = 15.0


def storage_problem(request: Request) -> str | None:
    """The station's word on its database now (None: usable, or no station to ask)."""
    station = getattr(request.app.state, "station", None)
    storage = getattr(station, "storage", None)
    blocked = getattr(storage, "blocked", None)
    return blocked() if callable(blocked) else None


def driver_line(exc: OperationalError) -> str:
    """The first line of the driver's own message (psycopg's run over several)."""
    return (str(getattr(exc, "orig", None) or exc).strip().splitlines() or ["connection error"])[0][:200]


def unavailable(why: str) -> HTTPException:
    return HTTPException(status_code=503, detail=f"the station's database is not available: {why}",
                         headers={"Retry-After": "5"})


async def db_call(request: Request, fn: Callable[..., T], *args: object, timeout_s: float | None = DB_READ_TIMEOUT_S,
                  **kwargs: object) -> T:
    """`fn(*args, **kwargs)` in the thread pool, refused or bounded as the module doc says."""
    why = storage_problem(request)
    if why is not None:
        raise unavailable(why)
    try:
        if timeout_s is None:
            return await run_in_threadpool(fn, *args, **kwargs)
        return await asyncio.wait_for(run_in_threadpool(fn, *args, **kwargs), timeout_s)
    except asyncio.TimeoutError:
        raise unavailable(f"no answer within {timeout_s:g} s") from None
    except StorageUnavailable as exc:
        raise unavailable(str(exc)) from None
    except OperationalError as exc:
        raise unavailable(driver_line(exc)) from None


__all__ = ["db_call", "driver_line", "storage_problem", "unavailable", "DB_READ_TIMEOUT_S"]
