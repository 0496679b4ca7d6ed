"""DUT history by serial number."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.concurrency import run_in_threadpool

from web.auth import require_read
from web.schemas import DutOut, DutSummary, RunOut, error_responses
from web.views import clean, dut_view, not_found

router = APIRouter(prefix="/api/duts", tags=["duts"], responses=error_responses(401, 403, 404, 503))
Serial = Path(min_length=1, max_length=64, pattern=r"^[\x21-\x7e]+$", description="DUT serial number")


@router.get("", response_model=list[DutSummary], dependencies=[Depends(require_read)])
async def search_duts(
    request: Request,
    serial_like: str | None = Query(default=None, max_length=64, description="part of a serial number"),
    limit: int = Query(default=50, ge=1, le=500),
):
    return clean(await run_in_threadpool(request.app.state.repo.search_duts, serial_like, limit))


@router.get("/{serial}", response_model=DutOut, dependencies=[Depends(require_read)])
async def get_dut(request: Request, serial: str = Serial):
    dut = await run_in_threadpool(request.app.state.repo.dut, serial)
    if dut is None:
        raise not_found(f"DUT {serial}")
    return dut_view(dut)


@router.get("/{serial}/runs", response_model=list[RunOut], dependencies=[Depends(require_read)])
async def dut_runs(request: Request, serial: str = Serial):
    runs = await run_in_threadpool(request.app.state.repo.runs_of_dut, serial)
    if runs is None:
        raise not_found(f"DUT {serial}")
    return [clean(r) for r in runs]
