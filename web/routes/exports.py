"""Exports for a factory's yield and traceability tools (docs/exports.md): a stored batch (every
DUT run) or one run as STDF V4 or OCP Test & Validation JSON lines. Thin: the repository reads and
station/records/export_*.py write; a batch or run still running answers 409 (its verdicts are not
final), an unknown id 404."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Path, Request
from fastapi.responses import Response

from web.auth import require_read
from web.db_gate import db_call
from web.schemas import ErrorOut, error_responses
from web.views import not_found

router = APIRouter(prefix="/api", tags=["exports"], responses=error_responses(401, 403, 404, 422, 503))
BatchId = Path(ge=1, le=2**62, description="batch id")
RunId = Path(ge=1, le=2**62, description="run id")

STDF_TYPE = "application/octet-stream"  # STDF has no registered media type
OCPTV_TYPE = "application/x-ndjson"  # the OCPTV output is line-delimited JSON, one artifact per line
NOT_READY = {"model": ErrorOut, "description": "still running: its verdicts are not final yet"}
STDF_RESPONSES = {200: {"content": {STDF_TYPE: {}}, "description": "STDF V4, little-endian"}, 409: NOT_READY}
OCPTV_RESPONSES = {200: {"content": {OCPTV_TYPE: {}}, "description": "OCPTV 2.0 JSON lines, one testRun per DUT run"},
                   409: NOT_READY}


async def _export(request: Request, fmt: str, what: str, batch_id: int | None = None,
                  run_id: int | None = None) -> Response:
    from station.records.export_model import ExportNotReady

    try:
        data = await db_call(request, request.app.state.repo.export_file, fmt, batch_id, run_id)
    except ExportNotReady as exc:
        raise HTTPException(status_code=409, detail=str(exc)) from None
    if data is None:
        raise not_found(what)
    name = what.replace(" ", "-")
    media, suffix = (STDF_TYPE, "stdf") if fmt == "stdf" else (OCPTV_TYPE, "ocptv.json")
    return Response(data, media_type=media, headers={"Content-Disposition": f'attachment; filename="{name}.{suffix}"'})


@router.get("/batches/{batch_id}/export.stdf", dependencies=[Depends(require_read)], response_class=Response,
            responses=STDF_RESPONSES)
async def batch_stdf(request: Request, batch_id: int = BatchId):
    """Every DUT run of the batch as STDF V4: MIR with lot, part number, revision and work order;
    per DUT PIR, a PTR per judged measurement (limits, units) and PRR (serial, pass flag, bins)."""
    return await _export(request, "stdf", f"batch {batch_id}", batch_id=batch_id)


@router.get("/batches/{batch_id}/export.ocptv.json", dependencies=[Depends(require_read)], response_class=Response,
            responses=OCPTV_RESPONSES)
async def batch_ocptv(request: Request, batch_id: int = BatchId):
    """Every DUT run of the batch as OCP Test & Validation output: one testRun per run, each
    starting with its schemaVersion line; measurements with validators, one diagnosis per verdict."""
    return await _export(request, "ocptv", f"batch {batch_id}", batch_id=batch_id)


@router.get("/runs/{run_id}/export.stdf", dependencies=[Depends(require_read)], response_class=Response,
            responses=STDF_RESPONSES)
async def run_stdf(request: Request, run_id: int = RunId):
    """One DUT run as STDF V4 (one part)."""
    return await _export(request, "stdf", f"run {run_id}", run_id=run_id)


@router.get("/runs/{run_id}/export.ocptv.json", dependencies=[Depends(require_read)], response_class=Response,
            responses=OCPTV_RESPONSES)
async def run_ocptv(request: Request, run_id: int = RunId):
    """One DUT run as OCP Test & Validation output (one testRun)."""
    return await _export(request, "ocptv", f"run {run_id}", run_id=run_id)
