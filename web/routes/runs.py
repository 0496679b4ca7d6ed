"""One DUT run: details, segments, the log file (design 5.1 CSV) and a plot."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Path, Request, Response
from fastapi.concurrency import run_in_threadpool

from contracts.logfile import format_log
from web.auth import require_read
from web.db_gate import db_call
from web.diag_plots import BoundedCache, Busy
from web.plots import render_run_png
from web.schemas import RunOut, SegmentOut, error_responses
from web.views import clean, dut_view, not_found
from contracts.filenames import safe_name

router = APIRouter(prefix="/api/runs", tags=["runs"], responses=error_responses(
    401, 403, 404, 422, 429, 503, what={429: "too many plots being rendered: retry after Retry-After seconds"}))
RunId = Path(ge=1, le=2**62, description="run id")


@router.get("/{run_id}", response_model=RunOut, dependencies=[Depends(require_read)])
async def get_run(request: Request, run_id: int = RunId):
    run = await db_call(request, request.app.state.repo.run, run_id)
    if run is None:
        raise not_found(f"run {run_id}")
    return clean(run)


@router.get("/{run_id}/segments", response_model=list[SegmentOut], dependencies=[Depends(require_read)])
async def run_segments(request: Request, run_id: int = RunId):
    segs = await db_call(request, request.app.state.repo.segments, run_id)
    if segs is None:
        raise not_found(f"run {run_id}")
    return clean(segs)


@router.get(
    "/{run_id}/log.csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}, "description": "the run's log, design 5.1"}},
    dependencies=[Depends(require_read)],
)
async def run_log_csv(request: Request, run_id: int = RunId):
    log = await db_call(request, request.app.state.repo.run_log, run_id)
    if log is None:
        raise not_found(f"run {run_id}")
    text = await run_in_threadpool(format_log, log)
    name = f"{safe_name(log.serial or 'run')}-run{run_id}.csv"
    return Response(text, media_type="text/csv", headers={"Content-Disposition": f'attachment; filename="{name}"'})


def _plot(repo, run_id: int) -> bytes | None:
    run = repo.run(run_id)
    if run is None:
        return None
    log = repo.run_log(run_id)
    segs = repo.segments(run_id) or []
    axes = dut_view({"serial": run.get("serial") or "", "thermal": run.get("thermal")}).get("thermal")
    title = f"{run.get('serial') or ''}  run {run_id}  ({run.get('state') or ''})"
    if log is None:
        from contracts.logfile import DutLog
        import numpy as np

        log = DutLog(np.empty(0), np.empty((0, 3)), np.empty(0))
    return render_run_png(log, segs, axes, title=title)


@router.get(
    "/{run_id}/plot.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "raw and compensated acceleration, temperature, segments"}},
    dependencies=[Depends(require_read)],
)
async def run_plot(request: Request, run_id: int = RunId):
    """A finished run's plot is rendered once (LRU); any plot is refused with 429 + Retry-After
    while RUN_PLOTS_AT_ONCE others are being rendered (a render takes seconds of CPU)."""
    repo = request.app.state.repo
    run = await db_call(request, repo.run, run_id)
    if run is None:
        raise not_found(f"run {run_id}")
    finished = run.get("finished_at")
    key = (run_id, run.get("state"), str(finished), run.get("fault_reason"))
    try:
        png = await db_call(request, _plot_cache(request).get, key, lambda: _plot(repo, run_id), store=finished is not None, timeout_s=None)
    except Busy as exc:
        raise HTTPException(status_code=429, detail=str(exc), headers={"Retry-After": str(exc.retry_after_s)}) from None
    if png is None:
        raise not_found(f"run {run_id}")
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-cache"})


RUN_PLOT_CACHE_SIZE = 32
RUN_PLOTS_AT_ONCE = 2


def _plot_cache(request: Request) -> BoundedCache[bytes]:
    cache = getattr(request.app.state, "run_plot_cache", None)
    if cache is None:
        cache = request.app.state.run_plot_cache = BoundedCache("run plot", RUN_PLOT_CACHE_SIZE, RUN_PLOTS_AT_ONCE)
    return cache
