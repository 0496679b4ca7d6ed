"""Exports for a factory's yield and traceability tools (docs/exports.md): a stored batch (every
DUT run) or one run in each registered export format (station/records/export_formats.py: STDF V4,
OCP Test & Validation JSON lines, ...), at `/api/batches/{id}/export.SUFFIX` and
`/api/runs/{id}/export.SUFFIX`. Thin: the repository reads and the format's writer writes; a batch
or run still running answers 409 (its verdicts are not final), an unknown id 404, and so does a
suffix no format has (no route).

The routes are made per app from the registry (`build_router`, called by create_app), one pair per
format with its own media type in the OpenAPI, so a format registered before the app is created is
served and documented with no change here.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Path, Request
from fastapi.responses import Response

from station.records.export_formats import ExportFormat, export_formats
from web.auth import require_read
from web.db_gate import db_call
from web.schemas import ErrorOut, error_responses
from web.views import not_found

BatchId = Path(ge=1, le=2**62, description="batch id")
RunId = Path(ge=1, le=2**62, description="run id")

NOT_READY = {"model": ErrorOut, "description": "still running: its verdicts are not final yet"}


def responses_of(fmt: ExportFormat) -> dict:
    """The OpenAPI answers of a format's routes: its media type, and 409 while running."""
    return {200: {"content": {fmt.media_type: {}}, "description": fmt.description or fmt.title}, 409: NOT_READY}


async def _export(request: Request, fmt: ExportFormat, what: str, batch_id: int | None = None,
                  run_id: int | None = None) -> Response:
    from station.records.export_model import ExportNotReady

    try:
        data = await db_call(request, request.app.state.repo.export_file, fmt.name, batch_id, run_id)
    except ExportNotReady as exc:
        raise HTTPException(status_code=409, detail=str(exc)) from None
    if data is None:
        raise not_found(what)
    name = what.replace(" ", "-")
    return Response(data, media_type=fmt.media_type,
                    headers={"Content-Disposition": f'attachment; filename="{name}.{fmt.suffix}"'})


def _batch_route(fmt: ExportFormat):
    async def batch_export(request: Request, batch_id: int = BatchId):
        return await _export(request, fmt, f"batch {batch_id}", batch_id=batch_id)

    return batch_export


def _run_route(fmt: ExportFormat):
    async def run_export(request: Request, run_id: int = RunId):
        return await _export(request, fmt, f"run {run_id}", run_id=run_id)

    return run_export


def build_router(formats: dict[str, ExportFormat] | None = None) -> APIRouter:
    """The export routes of every format (default: the registered ones, as they are now)."""
    formats = export_formats() if formats is None else formats
    router = APIRouter(prefix="/api", tags=["exports"], responses=error_responses(401, 403, 404, 422, 503))
    for fmt in formats.values():
        router.add_api_route(f"/batches/{{batch_id}}/export.{fmt.suffix}", _batch_route(fmt), methods=["GET"],
                             name=f"batch_{fmt.name}", dependencies=[Depends(require_read)], response_class=Response,
                             responses=responses_of(fmt),
                             description=fmt.batch_doc or f"Every DUT run of the batch as {fmt.title}.")
    for fmt in formats.values():
        router.add_api_route(f"/runs/{{run_id}}/export.{fmt.suffix}", _run_route(fmt), methods=["GET"],
                             name=f"run_{fmt.name}", dependencies=[Depends(require_read)], response_class=Response,
                             responses=responses_of(fmt), description=fmt.run_doc or f"One DUT run as {fmt.title}.")
    return router
