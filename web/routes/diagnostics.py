"""Model diagnostics of a stored run (design 7) for the page: JSON, plots and the fitted model.

    GET /api/runs/{id}/diagnosis?add=EFFECT&add=...       design 5.2 JSON (+ staircase, flags)
    GET /api/runs/{id}/diagnosis/{plot}.png?add=...       one plot (station.diagnostics.plots.PLOTS)
    GET /api/runs/{id}/diagnosis/model.json?add=...       the fitted model (baseline + added effects)
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from station.diagnostics.effects import REGISTRY
from contracts.types import StationError
from web.auth import require_read
from web.db_gate import db_call
from web.diag_plots import PLOTS, Busy, DiagnosisCache, check_effects, report_json
from web.schemas import DiagnosisOut, DiagnosticModelOut, error_responses
from web.views import not_found
from contracts.filenames import safe_name

router = APIRouter(prefix="/api/runs", tags=["diagnostics"], responses=error_responses(
    401, 403, 404, 409, 422, 429, 503,
    what={404: "unknown run, run without a log, or unknown plot", 409: "the run's log cannot be diagnosed (too short, no temperature swing)",
          429: "too many diagnoses or plots running or waiting: retry after Retry-After seconds"}))
RunId = Path(ge=1, le=2**62, description="run id")
Add = Query(default=[], description="effect to add to the model (repeatable, in staircase order)",
            json_schema_extra={"items": {"type": "string", "enum": sorted(REGISTRY)}})


def _busy(exc: Busy) -> HTTPException:
    return HTTPException(status_code=429, detail=str(exc), headers={"Retry-After": str(exc.retry_after_s)})


def _cache(request: Request) -> DiagnosisCache:
    cache = getattr(request.app.state, "diagnosis_cache", None)
    if cache is None:
        cache = request.app.state.diagnosis_cache = DiagnosisCache()
    return cache


async def _report(request: Request, run_id: int, add: list[str]):
    try:
        effects = check_effects(add)
    except StationError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    repo = request.app.state.repo
    try:
        rep = await db_call(request, _cache(request).get, run_id, effects, lambda: repo.run_log(run_id), timeout_s=None)
    except StationError as exc:  # the log cannot be diagnosed (too short, no temperature swing)
        raise HTTPException(status_code=409, detail=f"run {run_id}: {exc}") from None
    except Busy as exc:
        raise _busy(exc) from None
    if rep is None:
        raise not_found(f"run {run_id} (or its log)")
    return rep


@router.get("/{run_id}/diagnosis", response_model=DiagnosisOut, dependencies=[Depends(require_read)])
async def run_diagnosis(request: Request, run_id: int = RunId, add: list[str] = Add):
    rep = await _report(request, run_id, add)
    return await run_in_threadpool(report_json, rep)


@router.get("/{run_id}/diagnosis/model.json", response_model=DiagnosticModelOut, dependencies=[Depends(require_read)])
async def run_diagnosis_model(request: Request, run_id: int = RunId, add: list[str] = Add):
    rep = await _report(request, run_id, add)
    model = rep.models()[0]
    return Response(
        _dumps(model.to_json()), media_type="application/json",
        headers={"Content-Disposition": f'attachment; filename="{safe_name(model.serial or "run")}-run{run_id}.model.json"'},
    )


@router.get(
    "/{run_id}/diagnosis/{plot}.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "a diagnosis plot"}},
    dependencies=[Depends(require_read)],
)
async def run_diagnosis_plot(request: Request, run_id: int = RunId, plot: str = Path(), add: list[str] = Add):
    if plot not in PLOTS:
        raise not_found(f"plot {plot!r} (known: {', '.join(PLOTS)})")
    rep = await _report(request, run_id, add)
    try:
        png = await run_in_threadpool(_cache(request).png, run_id, check_effects(add), plot, rep)
    except Busy as exc:
        raise _busy(exc) from None
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-cache"})


def _dumps(obj) -> str:
    import json

    return json.dumps(obj, indent=2) + "\n"
