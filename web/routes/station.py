"""Station-wide resources: health (open), slots, profiles."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool

from web.auth import require_read
from web.schemas import Health, ProfileOut, SlotOut
from web.views import call, clean, slot_view

router = APIRouter(prefix="/api", tags=["station"])


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
    return {"status": "ok", "version": __version__, "time": time.time(), "db": db_state}


@router.get("/slots", response_model=list[SlotOut], dependencies=[Depends(require_read)])
async def slots(request: Request):
    return [slot_view(s) for s in await call(request.app.state.station.slots_status)]


@router.get("/profiles", response_model=list[ProfileOut], dependencies=[Depends(require_read)])
async def profiles(request: Request):
    out = []
    for p in await call(request.app.state.station.profiles):
        out.append({"name": p} if isinstance(p, str) else clean(dict(p)))
    return out


@router.get("/me", dependencies=[], response_model=dict)
async def me(request: Request, principal=Depends(require_read)):
    """Who the token belongs to (name and role): the page shows it and hides what the role may not do."""
    return {"name": principal.name, "role": principal.role}
