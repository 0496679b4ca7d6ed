"""Records of the station: the audit trail (admin), yield, SPC and the failure Pareto with their
filters and CSVs, replays. Thin: the repository reads, station/records/spc.py and
pareto.py compute, station/replay compared."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from datetime import date, datetime, time, timedelta, timezone

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.responses import Response

from web.auth import require_admin, require_read
from web.db_gate import db_call
from station.records.spc_rules import RULE_NAMES
from web.schemas import error_responses
from web.schemas_records import AuditEntry, ParetoOut, ReplayEntry, ReplayOut, SpcOut
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
    return clean(await db_call(request, request.app.state.repo.audit_list, limit, before_id, station))


# ---- yield, SPC and failure Pareto (station/records/spc.py, pareto.py) ------------------------------------
SPC_LIMIT = 5000  # the newest judged runs an answer covers (after the filters)
UNSPECIFIED = "(unspecified)"  # filter value: runs whose batch carried no part number / work order


@dataclass(frozen=True)
class Filters:
    date_from: date | None
    date_to: date | None
    product: str | None
    station: str | None
    work_order: str | None
    limit: int

    def to_json(self) -> dict:
        return {"from": self.date_from and self.date_from.isoformat(), "to": self.date_to and self.date_to.isoformat(),
                "product": self.product, "station": self.station, "work_order": self.work_order, "limit": self.limit}

    def query(self) -> dict:
        return {k: v for k, v in self.to_json().items() if v is not None and k != "limit"}


DAY = r"^\d{4}-\d{2}-\d{2}$"  # an ISO day only: pydantic's lax `date` would take 0 as 1970-01-01


def _day(value: str | None, name: str) -> date | None:
    if not value:
        return None
    try:
        return date.fromisoformat(value)
    except ValueError:
        raise HTTPException(status_code=422, detail=f"{name} {value!r} is no calendar day (YYYY-MM-DD)") from None


def filters(
    day_from: str | None = Query(default=None, alias="from", pattern=DAY, description="judged on or after this day "
                                 "(UTC, ISO date YYYY-MM-DD)"),
    day_to: str | None = Query(default=None, alias="to", pattern=DAY, description="judged on or before this day "
                               "(UTC, ISO date YYYY-MM-DD, inclusive)"),
    product: str | None = Query(default=None, max_length=140, description="part number and revision as listed in "
                                "options.products ('PN rev R'); '(unspecified)' = runs without a part number"),
    station: str | None = Query(default=None, max_length=64, description="only this station's runs"),
    work_order: str | None = Query(default=None, max_length=64, description="only this work order's runs; "
                                   "'(unspecified)' = runs without one"),
    limit: int = Query(default=SPC_LIMIT, ge=2, le=100_000, description="the newest N judged runs under the filters"),
) -> Filters:
    """The filters of every records answer (SPC, Pareto, their CSV): one definition, so the CSV is
    computed under exactly the filters of the page."""
    date_from, to = _day(day_from, "from"), _day(day_to, "to")
    if date_from and to and date_from > to:
        raise HTTPException(status_code=422, detail=f"from {date_from.isoformat()} is after to {to.isoformat()}")
    return Filters(date_from, to, product or None, station or None, work_order or None, limit)


def _utc_day(d: date) -> datetime:
    return datetime.combine(d, time(), tzinfo=timezone.utc)


def _options(facets: list[dict]) -> dict:
    def opts(key: str, empty: str) -> list[dict]:
        runs: dict[str, int] = {}
        for f in facets:
            runs[f[key]] = runs.get(f[key], 0) + f["runs"]
        return [{"value": v or UNSPECIFIED, "label": v or empty, "runs": n} for v, n in sorted(runs.items())]
    return {"products": opts("product", "unspecified product"), "stations": opts("station", "unnamed station"),
            "work_orders": opts("work_order", "no work order")}


async def _runs(request: Request, f: Filters) -> tuple[list[dict], dict]:
    """The judged runs under the filters (oldest first) and the filter choices of the date range."""
    repo = request.app.state.repo
    day_from = _utc_day(f.date_from) if f.date_from else None
    day_to = _utc_day(f.date_to + timedelta(days=1)) if f.date_to else None
    facets = await db_call(request, repo.judged_facets, day_from, day_to)
    kw: dict = {"judged_from": day_from, "judged_to": day_to}
    if f.product == UNSPECIFIED:
        kw["part_number"] = ""
    elif f.product:  # the listed product's own part number and revision (a ' rev ' inside a part number is fine)
        pn, rev = next(((x["part_number"], x["part_revision"]) for x in facets if x["product"] == f.product),
                       (f.product, None))
        kw.update(part_number=pn, part_revision=rev)
    if f.work_order:
        kw["work_order"] = "" if f.work_order == UNSPECIFIED else f.work_order
    runs = await db_call(request, repo.judged_runs, f.limit, f.station, **kw)
    if f.product and f.product != UNSPECIFIED:
        runs = [r for r in runs if r.get("product") == f.product]
    return runs, _options(facets)


GROUP = Query(default=None, max_length=600, description="the group (product x limits version) to chart, a `key` "
              "from `groups` (default: the group with the newest run)")
PARAM = Query(default=None, max_length=80, pattern=r"^[A-Za-z0-9_]+(:[a-z])?$",
              description="a judged measurement, 'measurement' or 'measurement:axis', e.g. tdb_mg_per_c:z "
                          "(default: the group's first one)")


async def _spc(request: Request, f: Filters, group: str | None, parameter: str | None):
    from station.records import spc
    runs, options = await _runs(request, f)
    try:
        view = spc.spc_view(runs, group, parameter)
    except LookupError as e:
        raise HTTPException(status_code=404, detail=str(e)) from None
    return runs, options, view


CSV_OK = {200: {"content": {"text/csv": {}}, "description": "the rows and columns of the table the Records view shows"}}
# A `from`/`to` the schema's YYYY-MM-DD pattern lets through can still be no calendar day (0000-00-00,
# 2026-02-30), and each can be valid alone with `from` after `to`: 422, listed with those words.
DAYS_422 = error_responses(422, what={422: "invalid input, also schema-valid ones: a from/to that is no calendar day "
                                           "(0000-00-00, 2026-02-30), or from after to"})


@router.get("/records/spc", response_model=SpcOut, dependencies=[Depends(require_read)], responses=DAYS_422)
@router.get("/spc", response_model=SpcOut, dependencies=[Depends(require_read)], deprecated=True, responses=DAYS_422,
            summary="Spc Chart (old address of /api/records/spc, same answer)")
async def spc_chart(request: Request, f: Filters = Depends(filters), group: str | None = GROUP,
                    parameter: str | None = PARAM):
    """Individuals/moving-range chart of ONE parameter in ONE group (product x limits version):
    each point judged by its own run's limits and named by the run rules it breaks; Cpk/Ppk from
    n >= 25 with a 95 % interval; histogram, per-slot trend; the groups under the filters, the
    filter choices, and yield per batch, day, product, limits set and station."""
    from station.records import spc
    runs, options, view = await _spc(request, f, group, parameter)
    out = view.report.to_json()
    out.update(parameters=view.parameters, parameter_labels=view.labels, groups=[asdict(g) for g in view.groups],
               rules=dict(RULE_NAMES), columns=spc.csv_columns(view.report), filters=f.to_json(), options=options,
               **{"yield": {by: [asdict(y) for y in spc.yields(runs, by)] for by in spc.YIELD_BY}})
    return clean(out)




@router.get("/records/spc.csv", dependencies=[Depends(require_read)], response_class=Response,
            responses={**CSV_OK, **DAYS_422})
@router.get("/spc.csv", dependencies=[Depends(require_read)], response_class=Response, responses={**CSV_OK, **DAYS_422},
            deprecated=True, summary="Spc Csv (old address of /api/records/spc.csv)")
async def spc_csv(request: Request, f: Filters = Depends(filters), group: str | None = GROUP,
                  parameter: str | None = PARAM):
    """The points table of /api/records/spc under the same query: one row per judged run."""
    from station.records import spc
    _runs_, _options_, view = await _spc(request, f, group, parameter)
    g = view.report.group
    name = safe_name("-".join(x for x in (view.report.parameter or "none", g.product if g else "",
                                          g.limits_version if g else "") if x))
    return Response(spc.csv_text(view.report), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="spc-{name}.csv"'})


@router.get("/records/pareto", response_model=ParetoOut, dependencies=[Depends(require_read)], responses=DAYS_422)
async def failure_pareto(request: Request, f: Filters = Depends(filters)):
    """Failure Pareto under the filters: fail/error checks per parameter, and one cause per run
    judged fail or error, by name (label mismatch, plate never arrived, link lost, not measured,
    limit: TDB, ...), each most frequent first with cumulative percent."""
    from station.records import pareto
    runs, options = await _runs(request, f)
    out = pareto.pareto(runs).to_json()
    out.update(columns=list(pareto.CSV_COLUMNS), filters=f.to_json(), options=options)
    return clean(out)


@router.get("/records/pareto.csv", dependencies=[Depends(require_read)], response_class=Response,
            responses={**CSV_OK, **DAYS_422})
async def failure_pareto_csv(request: Request, f: Filters = Depends(filters)):
    """The Pareto table of /api/records/pareto under the same query (checks, then causes)."""
    from station.records import pareto
    runs, _options_ = await _runs(request, f)
    return Response(pareto.csv_text(pareto.pareto(runs)), media_type="text/csv",
                    headers={"Content-Disposition": 'attachment; filename="failure-pareto.csv"'})


# ---- replays (station/replay) -------------------------------------------------------------------
@router.get("/replays", response_model=list[ReplayEntry], dependencies=[Depends(require_read)])
async def list_replays(request: Request, limit: int = Query(default=50, ge=1, le=1000)):
    """Replay batches (`station replay`), newest first: source, how many DUTs changed, verdict changes."""
    return clean(await db_call(request, request.app.state.repo.replays, limit))


@router.get("/replays/{batch_id}", response_model=ReplayOut, dependencies=[Depends(require_read)])
async def get_replay(request: Request, batch_id: int = Path(ge=1, le=2**62)):
    """One replay's comparison with the recording: every changed number and word per DUT."""
    out = await db_call(request, request.app.state.repo.replay, batch_id)
    if out is None:
        raise HTTPException(status_code=404, detail=f"batch {batch_id} is no replay (or does not exist)")
    return clean(out)
