"""DUT history by serial number."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.responses import Response

from web.auth import require_read
from web.db_gate import db_call
from web.schemas import DutOut, DutSummary, ErrorOut, RunOut, error_responses
from web.views import clean, dut_view, not_found
from contracts.filenames import safe_name

router = APIRouter(prefix="/api/duts", tags=["duts"], responses=error_responses(401, 403, 404, 503))
Serial = Path(min_length=1, max_length=64, pattern=r"^[\x21-\x7e]+$", description="DUT serial number")


@router.get("", response_model=list[DutSummary], dependencies=[Depends(require_read)])
async def search_duts(
    request: Request,
    serial_like: str | None = Query(default=None, max_length=64, description="part of a serial number"),
    limit: int = Query(default=50, ge=1, le=500),
):
    return clean(await db_call(request, request.app.state.repo.search_duts, serial_like, limit))


@router.get("/{serial}", response_model=DutOut, dependencies=[Depends(require_read)])
async def get_dut(request: Request, serial: str = Serial):
    dut = await db_call(request, request.app.state.repo.dut, serial)
    if dut is None:
        raise not_found(f"DUT {serial}")
    return dut_view(dut)


@router.get("/{serial}/runs", response_model=list[RunOut], dependencies=[Depends(require_read)])
async def dut_runs(request: Request, serial: str = Serial):
    runs = await db_call(request, request.app.state.repo.runs_of_dut, serial)
    if runs is None:
        raise not_found(f"DUT {serial}")
    return [clean(r) for r in runs]


@router.get("/{serial}/certificate.pdf", dependencies=[Depends(require_read)], response_class=Response,
            responses={200: {"content": {"application/pdf": {}}, "description": "the certificate (A4, as many pages as its checks need)"},
                       409: {"model": ErrorOut, "description": "the DUT has no stored result yet"}})
async def dut_certificate(request: Request, serial: str = Serial):
    """Calibration certificate of the DUT's result run (its latest valid attempt): identity,
    station, operator, firmware, profile and limits version, coefficients with uncertainties,
    verdict and grade, fit plot (station/records/certificate.py)."""
    try:
        pdf = await db_call(request, request.app.state.repo.certificate_pdf, serial)
    except LookupError as exc:
        raise HTTPException(status_code=409, detail=str(exc).strip("'\"")) from None
    if pdf is None:
        raise not_found(f"DUT {serial}")
    return Response(pdf, media_type="application/pdf",
                    headers={"Content-Disposition": f'inline; filename="certificate-{safe_name(serial)}.pdf"'})
