"""Records of the station (issues 13, 16): the audit trail (admin), yield and SPC, replays. Thin:
the repository reads, station/records/spc.py computes, station/replay compared."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from web.auth import require_admin, require_read
from web.schemas import AuditEntry, ReplayEntry, ReplayOut, SpcOut, error_responses
from web.views import clean
from contracts.filenames import safe_name

router = APIRouter(prefix="/api", tags=["records"], responses=error_responses(401, 403, 404, 422, 503))


@router.get("/audit", response_model=list[AuditEntry], dependencies=[Depends(require_admin)])
async def audit_trail(
    request: Request,
    limit: int = Query(default=100, ge=1, le=1000),
    before_id: int | None = Query(default=None, ge=1, le=2**62, description="page back: the last id of a page"),
    station: str | None = Query(default=None, max_length=64, description="only this station's entries"),
):
    """Who did what through the API (batch start, abort, prompt answers, resume), newest first."""
    return clean(await run_in_threadpool(request.app.state.repo.audit_list, limit, before_id, station))


# ---- yield and SPC (station/records/spc.py) -----------------------------------------------------------------
SPC_LIMIT = 5000  # the newest judged runs an SPC answer covers


async def _report(request: Request, parameter: str | None, station: str | None, limit: int):
    from station.records import spc
    runs = await run_in_threadpool(request.app.state.repo.judged_runs, limit, station)
    params = spc.parameters(runs)
    if parameter is None:
        parameter = params[0] if params else ""
    elif parameter not in params:
        raise HTTPException(status_code=404, detail=f"parameter {parameter!r} not found in the judged runs; "
                            f"known: {', '.join(params) or 'none'}")
    return runs, params, spc.spc_report(runs, parameter)


PARAM = Query(default=None, max_length=80, pattern=r"^[A-Za-z0-9_]+(:[a-z])?$",
              description="a judged measurement, 'measurement' or 'measurement:axis', e.g. tdb_mg_per_c:z "
                          "(default: the first one)")
STATION = Query(default=None, max_length=64, description="only this station's runs")
LIMIT = Query(default=SPC_LIMIT, ge=2, le=100_000, description="the newest N judged runs")


@router.get("/spc", response_model=SpcOut, dependencies=[Depends(require_read)])
async def spc_chart(request: Request, parameter: str | None = PARAM, station: str | None = STATION,
                    limit: int = LIMIT):
    """Individuals/moving-range chart, Cpk/Ppk against the spec limits the runs were judged by,
    histogram, per-slot trend of one parameter; yield per batch, day, product and station."""
    from station.records import spc
    runs, params, report = await _report(request, parameter, station, limit)
    out = report.to_json()
    out["parameters"] = params
    out["yield"] = {by: [asdict(y) for y in spc.yields(runs, by)] for by in ("batch", "day", "product", "station")}
    return clean(out)


@router.get("/spc.csv", dependencies=[Depends(require_read)], response_class=Response,
            responses={200: {"content": {"text/csv": {}}, "description": "one row per judged run"}})
async def spc_csv(request: Request, parameter: str | None = PARAM, station: str | None = STATION, limit: int = LIMIT):
    from station.records import spc
    _runs, _params, report = await _report(request, parameter, station, limit)
    name = safe_name(report.parameter or "none")
    return Response(spc.csv_text(report), media_type="text/csv",
                             headers={"Content-Disposition": f'attachment; filename="spc-{name}.csv"'})


# ---- replays (station/replay) -------------------------------------------------------------------
@router.get("/replays", response_model=list[ReplayEntry], dependencies=[Depends(require_read)])
async def list_replays(request: Request, limit: int = Query(default=50, ge=1, le=1000)):
    """Replay batches (`station replay`), newest first: source, how many DUTs changed, verdict changes."""
    return clean(await run_in_threadpool(request.app.state.repo.replays, limit))


@router.get("/replays/{batch_id}", response_model=ReplayOut, dependencies=[Depends(require_read)])
async def get_replay(request: Request, batch_id: int = Path(ge=1, le=2**62)):
    """One replay's comparison with the recording: every changed number and word per DUT."""
    out = await run_in_threadpool(request.app.state.repo.replay, batch_id)
    if out is None:
        raise HTTPException(status_code=404, detail=f"batch {batch_id} is no replay (or does not exist)")
    return clean(out)
