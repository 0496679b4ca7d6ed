"""Station-wide resources: health (open), slots, profiles."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool

from web.auth import require_read
from web.schemas import Health, Me, ProfileOut, SlotOut, error_responses
from web.views import call, clean, slot_view

router = APIRouter(prefix="/api", tags=["station"])
AUTHED = error_responses(401, 403)


@router.get("/health", response_model=Health)
async def health(request: Request):
    from web import __version__

    repo = request.app.state.repo
    db_state = None
    if repo is not None:
        try:
            db_state = await run_in_threadpool(repo.health)
        except Exception as exc:  # noqa: BLE001 - health reports, never raises
            db_state = f"error: {type(exc).__name__}"
    lamp = None
    station = getattr(request.app.state, "station", None)
    if station is not None and hasattr(station, "lamp_status"):
        lamp = station.lamp_status()
    if station is not None and hasattr(station, "storage_status") and db_state == "ok":
        db_state = station.storage_status()  # reads may work while writes fail (disk full)
    return {"status": "ok", "version": __version__, "time": time.time(), "db": db_state, "lamp": lamp}


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
