"""Station-wide resources: health (open), slots, profiles."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool

from web.auth import require_read
from web.repo import NoRepository
from web.schemas import Health, Me, ProfileOut, SlotOut, error_responses
from web.views import call, clean, slot_view

router = APIRouter(prefix="/api", tags=["station"])
AUTHED = error_responses(401, 403)
HEALTH_DB_TIMEOUT_S = 1.0


@router.get("/health", response_model=Health)
async def health(request: Request):
    """Never waits on the database: with a station, its storage state (the database probe's last
    answer, the writer, the journal); without one, the repository's check, bounded to 1 s."""
    from web import __version__

    repo = request.app.state.repo
    station = getattr(request.app.state, "station", None)
    db_state = None
    if repo is None or isinstance(repo, NoRepository):
        db_state = None if repo is None else repo.health()
    elif station is not None and hasattr(station, "storage_status"):
        db_state = station.storage_status()
    else:
        try:
            db_state = await asyncio.wait_for(run_in_threadpool(repo.health), HEALTH_DB_TIMEOUT_S)
        except asyncio.TimeoutError:
            db_state = f"error: database not answering within {HEALTH_DB_TIMEOUT_S:g} s"
        except Exception as exc:  # noqa: BLE001 - health reports, never raises
            db_state = f"error: {type(exc).__name__}"
    lamp = None
    if station is not None and hasattr(station, "lamp_status"):
        lamp = station.lamp_status()
    waiting = station.storage.waiting() if station is not None and hasattr(station, "storage") else None
    intake = station.intake_status() if station is not None and hasattr(station, "intake_status") else None
    return {"status": "ok", "version": __version__, "time": time.time(), "db": db_state, "lamp": lamp,
            "forwarding": waiting, "intake": intake}


@router.get("/slots", response_model=list[SlotOut], responses=AUTHED, dependencies=[Depends(require_read)])
async def slots(request: Request):
    return [slot_view(s) for s in await call(request.app.state.station.slots_status)]


@router.get("/profiles", response_model=list[ProfileOut], responses=AUTHED, dependencies=[Depends(require_read)])
async def profiles(request: Request):
    """Every profile with its description, analysis kind and step count."""
    station = request.app.state.station
    info = getattr(station, "profiles_info", None)
    listed = await call(info) if info is not None else await call(station.profiles)
    return [{"name": p} if isinstance(p, str) else clean(dict(p)) for p in listed]


@router.get("/me", response_model=Me, responses=AUTHED)
async def me(request: Request, principal=Depends(require_read)):
    """Who the token belongs to (name and role): the page shows it and hides what the role may not do."""
    return {"name": principal.name, "role": principal.role}
