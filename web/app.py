"""The station's web app: REST API (design 5.3), server-sent events, operator page, MES outbox.

`create_app(station)` builds the FastAPI app around the daemon's `Station` facade; the daemon runs
it with uvicorn in its own event loop (web/server.py `serve_web`, also what the tests start), so
routes call the facade directly.
"""

from __future__ import annotations

import logging
import re
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from contracts.types import StationError
from web import __version__
from web.auth import TokenStore, install_log_redaction
from web.guard import DEFAULT_MAX_BODY_BYTES, RequestGuard
from web.mes_outbox import MesOutbox, OutboxConfig
from web.db_gate import driver_line, unavailable
from web.repo import NoRepository, WebRepository
from web.routes import batches, duts, events, results, runs, station as station_routes
from web.routes import diagnostics as diagnostics_routes
from web.routes import records as records_routes
from web.routes import exports as exports_routes
from web.schemas import install_openapi
from web import metrics
from web.sse import DEFAULT_MAX_EVENT_STREAMS

STATIC_DIR = Path(__file__).parent / "static"
# The station's icon: a thermometer-red dot on the page's dark blue (served as /favicon.ico).
FAVICON_SVG = (b'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 16 16">'
               b'<rect width="16" height="16" rx="3" fill="#1d3557"/><circle cx="8" cy="8" r="4" fill="#e63946"/></svg>')
log = logging.getLogger("station.web")

# The page loads only its own files: no CDN, no inline script.
CSP = "default-src 'self'; img-src 'self' data: blob:; style-src 'self'; script-src 'self'; connect-src 'self'"


def _validation_message(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors():
        if err.get("type") == "json_invalid":
            why = (err.get("ctx") or {}).get("error", "")
            parts.append(f"body: not valid JSON{': ' + str(why) if why else ''}")
            continue
        loc = ".".join(str(x) for x in err.get("loc", ()) if x != "body") or "body"
        parts.append(f"{loc}: {err.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


class SecurityHeaders:
    """Pure ASGI middleware (no per-request task as with @app.middleware("http"), and it leaves SSE
    streams alone): adds the CSP and nosniff headers to every HTTP response that has none."""

    _ADD = ((b"content-security-policy", CSP.encode()), (b"x-content-type-options", b"nosniff"))

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        static = scope.get("path", "").startswith("/static/")

        async def send_with_headers(message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers") or [])
                present = {k.lower() for k, _ in headers}
                headers += [(k, v) for k, v in self._ADD if k not in present]
                if static and b"cache-control" not in present:  # revalidate (ETag): a kiosk page
                    headers.append((b"cache-control", b"no-cache"))  # picks up an upgrade at once
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def default_repository(station) -> WebRepository:
    db = getattr(station, "db", None)
    if db is None or not hasattr(db, "engine"):  # a station-shaped test double without a database
        return NoRepository()
    from web.db_repo import DbRepository

    return DbRepository(db)


def create_app(
    station,
    *,
    repo: WebRepository | None = None,
    tokens: TokenStore | None = None,
    outbox: OutboxConfig | None | bool = True,
    sse_interval_s: float = 0.5,
    max_body_bytes: int | None = None,
    max_event_streams: int | None = None,
) -> FastAPI:
    """station: the daemon's facade (station.daemon.supervisor.Station or anything with its methods).

    repo: storage for history/MES (default: built from station.db); tokens: default from
    station.config; outbox: True = from config ([mes] webhook_url), an OutboxConfig, or False/None.
    max_body_bytes / max_event_streams: default from station.config [http].
    """
    config = getattr(station, "config", None)
    if repo is None:
        repo = default_repository(station)
    if tokens is None:
        tokens = TokenStore.from_config(config)
    if outbox is True:
        outbox = OutboxConfig.from_config(config)
    install_log_redaction()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        worker = None
        if outbox and not isinstance(repo, NoRepository):
            worker = MesOutbox(repo, outbox, bus=getattr(station, "bus", None))
            await worker.start()
            log.info("MES outbox delivering to %s", re.sub(r"//[^/@]*@", "//***@", outbox.url))  # no credentials in logs
        app.state.outbox = worker
        try:
            yield
        finally:
            if worker is not None:
                await worker.stop()

    app = FastAPI(
        title="Thermal calibration station",
        version=__version__,
        description="REST API of the MEMS accelerometer thermal calibration station (design 5.3). "
        "Send `Authorization: Bearer <token>`; roles: operator, mes, admin.",
        lifespan=lifespan,
        docs_url=None,  # FastAPI's Swagger UI and ReDoc load from a CDN: /docs is served below instead
        redoc_url=None,
    )
    app.state.station = station
    app.state.repo = repo
    app.state.tokens = tokens
    app.state.sse_interval_s = sse_interval_s
    app.state.outbox = None
    http_cfg = getattr(config, "http", None)
    if max_body_bytes is None:
        max_body_bytes = getattr(http_cfg, "max_body_bytes", None) or DEFAULT_MAX_BODY_BYTES
    if max_event_streams is None:
        max_event_streams = getattr(http_cfg, "max_event_streams", None) or DEFAULT_MAX_EVENT_STREAMS
    app.state.max_event_streams = int(max_event_streams)

    @app.exception_handler(RequestValidationError)
    async def _on_validation(request: Request, exc: RequestValidationError):
        return JSONResponse(
            status_code=422,
            content={"detail": _validation_message(exc), "errors": _jsonable_errors(exc)},
        )

    @app.exception_handler(StarletteHTTPException)
    async def _on_http_error(request: Request, exc: StarletteHTTPException):
        if exc.status_code == 405:  # Starlette names only the first matching route's methods
            exc.headers = {**(exc.headers or {}), "Allow": ", ".join(_allowed_methods(app, request.scope))}
        return await http_exception_handler(request, exc)

    @app.exception_handler(OperationalError)
    async def _on_database_down(request: Request, exc: OperationalError):
        # a route that reached the database through the station (a stored batch's status): the
        # database is down or hung, which is no bug of the request (web/db_gate.py)
        http = unavailable(driver_line(exc))
        return JSONResponse(status_code=503, content={"detail": http.detail}, headers=http.headers)

    @app.exception_handler(StationError)
    async def _on_station_error(request: Request, exc: StationError):
        return JSONResponse(status_code=409, content={"detail": str(exc)})

    app.add_middleware(RequestGuard, max_body_bytes=max_body_bytes)  # token and size before the body
    app.add_middleware(SecurityHeaders)  # added last = outermost: its headers go on the guard's answers too

    for module in (station_routes, batches, duts, runs, results, events):
        app.include_router(module.router)
    app.include_router(diagnostics_routes.router)  # model diagnostics of stored runs (design 7)
    app.include_router(records_routes.router)  # audit trail, yield and SPC (docs/records.md)
    app.include_router(exports_routes.build_router())  # every registered export format (STDF, OCPTV, ...)
    app.include_router(metrics.build_router(station, __version__))  # GET /metrics for plant IT (docs/metrics.md)
    results.register_webhooks(app)  # the MES webhook payload in the OpenAPI, so an MES integrator reads it there

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    async def index():
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon():
        """Browsers ask for it on every page: answered (a small SVG) instead of a 404 in every log."""
        return Response(FAVICON_SVG, media_type="image/svg+xml", headers={"Cache-Control": "max-age=86400"})

    @app.get("/docs", include_in_schema=False)
    async def api_docs():
        """The API reference, rendered from /openapi.json by the station's own script."""
        return FileResponse(STATIC_DIR / "api.html", headers={"Cache-Control": "no-cache"})

    install_openapi(app)
    return app


def _allowed_methods(app: FastAPI, scope) -> list[str]:
    """Every method some route serves at this path (for the Allow header of a 405): asks each
    route whether it would fully match the request with that method (routers included with a
    prefix answer for their own routes)."""
    from starlette.routing import Match

    allowed = []
    for method in ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"):
        probe = {**scope, "method": method}
        if any(route.matches(probe)[0] == Match.FULL for route in app.router.routes):
            allowed.append(method)
    return allowed


def _jsonable_errors(exc: RequestValidationError) -> list[dict]:
    out = []
    for err in exc.errors():
        out.append({"loc": [str(x) for x in err.get("loc", ())], "msg": str(err.get("msg", "")), "type": str(err.get("type", ""))})
    return out

