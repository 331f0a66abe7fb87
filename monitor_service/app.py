"""The FastAPI application factory."""
from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import os
import signal
import sys
import threading
import time

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Route

from monitor_service import db
from monitor_service.alerts import webhook_loop
from monitor_service.auth import KeyCache, ensure_admin_key
from monitor_service.ingest import IngestStore
from monitor_service.metrics import REQUEST_SECONDS
from monitor_service.routers import alerts, calibrations, dashboard, episodes, health, ingest, keys, tasks
from monitor_service.routers.ingest import IngestFastPath
from monitor_service.schemas import ERROR_MEANING, Error
from monitor_service.settings import MonitorSettings, unknown_variables

log = logging.getLogger(__name__)


class BodyLimit:
    """Pure ASGI middleware: refuse bodies over ``max_bytes`` with 413, by Content-Length or while streaming."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        message = (
            f"request body exceeds the {self.max_bytes}-byte limit; split it into smaller batches "
            "(or raise JEPA_MONITOR_MAX_BODY_BYTES)"
        )
        for name, value in scope.get("headers", []):
            if name == b"content-length" and value.isdigit() and int(value) > self.max_bytes:
                return await JSONResponse({"detail": message}, 413)(scope, receive, send)
        seen = 0

        class TooLarge(Exception):
            pass

        async def limited_receive():
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.max_bytes:
                    raise TooLarge
            return msg

        try:
            await self.app(scope, limited_receive, send)
        except* TooLarge:  # except*: task groups inside the stack may wrap it in an ExceptionGroup
            await JSONResponse({"detail": message}, 413)(scope, receive, send)


class RequestTimer:
    """Pure ASGI middleware observing every HTTP request's latency in the Prometheus histogram."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start = time.perf_counter()
        try:
            await self.app(scope, receive, send)
        finally:
            REQUEST_SECONDS.observe(time.perf_counter() - start)


PUBLIC_PATHS = {"/healthz", "/readyz"}
SUPERVISOR_ENV = "JEPA_MONITOR_SUPERVISOR_PID"   # set by `jepa-monitor serve --workers N` for its workers


def exit_with_parent(parent_pid: int, poll_s: float = 0.5) -> None:
    """End this worker (SIGTERM: uvicorn's graceful shutdown) as soon as its supervising process is gone, even
    after a SIGKILL, so a restarted service never meets an orphan holding its port.

    Linux delivers the signal itself (prctl PR_SET_PDEATHSIG); a watcher thread covers other systems and the
    moment before prctl took effect.
    """
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)   # 1 = PR_SET_PDEATHSIG

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def openapi_with_errors(app: FastAPI) -> dict:
    """The OpenAPI document as the server answers: every 4xx is ``Error`` ({"detail": "..."}, 422 included);
    routes behind a key document 401 and 403, routes with a body or parameters 400 / 413 / 422."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components["Error"] = Error.model_json_schema()
    error = {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}
    for path, operations in schema["paths"].items():
        for op in operations.values():
            for content in op.get("requestBody", {}).get("content", {}).values():
                components.update(content.get("schema", {}).pop("$defs", {}))
            codes = set() if path in PUBLIC_PATHS else {401, 403}
            if "requestBody" in op:
                codes |= {400, 413, 422}
            if op.get("parameters"):
                codes |= {400, 422}
            responses = op.setdefault("responses", {})
            codes |= {int(c) for c in responses if c.startswith("4")}
            for code in codes:
                responses[str(code)] = {"description": ERROR_MEANING[code], "content": error}
    for unused in ("HTTPValidationError", "ValidationError"):
        components.pop(unused, None)
    app.openapi_schema = schema
    return schema


def create_app(settings: MonitorSettings | None = None) -> FastAPI:
    """Build the service: storage (migrated to head unless disabled), auth bootstrap, routers and background tasks."""
    settings = settings or MonitorSettings()
    for warning in unknown_variables():
        log.warning(warning)
    db.check_database_url(settings.database_url, create=settings.create_database)
    supervisor = os.environ.get(SUPERVISOR_ENV, "")
    if supervisor.isdigit():   # a worker of `serve --workers N`
        if int(supervisor) != os.getppid():
            raise SystemExit(f"the supervising process {supervisor} ended while this worker started; not serving")
        exit_with_parent(int(supervisor))
    engine = db.make_engine(settings.database_url)
    in_use = db.mark_sqlite_in_use(settings.database_url)   # `db restore` refuses while a server holds this
    if settings.run_migrations:
        db.upgrade(engine)
    make_session = db.make_sessionmaker(engine)
    if settings.admin_key:
        with make_session() as session:
            ensure_admin_key(session, settings.admin_key)
            session.commit()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        # Only a service with webhooks configured polls for deliveries.
        task = (asyncio.create_task(webhook_loop(make_session, settings, app.state.stop)) if settings.webhook_urls
                else None)
        try:
            yield
        finally:
            app.state.stop.set()
            if task is not None:
                await task
            engine.dispose()
            if in_use is not None:
                in_use.close()

    app = FastAPI(
        title="JEPA Policy monitor",
        version="0.1.0",
        description="Future-consistency monitor (paper Sec. 3.6, 4.10): ingest, score, calibrate per task, alert.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessionmaker = make_session
    app.state.read_sessionmaker = db.make_sessionmaker(engine, read_only=True)
    app.state.ingest = IngestStore(engine, settings)   # the ingest path and its episode state (ingest.py)
    app.state.key_cache = KeyCache()
    # SQLite has one writer; queueing writers of this process on a lock hands over at once, where SQLite's own
    # busy handler would sleep and poll (long tails). Other worker processes still queue on busy_timeout.
    app.state.write_lock = threading.Lock() if engine.dialect.name == "sqlite" else contextlib.nullcontext()
    app.state.stop = asyncio.Event()

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code != 405:
            return await http_exception_handler(request, exc)
        # Several routes share a path (GET and POST /v1/keys): Allow names every method of the path, not only
        # those of the route that answered.
        allowed = sorted({m for r in app.routes if isinstance(r, Route) and r.matches(request.scope)[0] != Match.NONE
                          for m in r.methods or ()})
        return JSONResponse({"detail": f"{request.method} is not allowed on {request.url.path}; use "
                             f"{', '.join(allowed)}"}, 405, headers={"Allow": ", ".join(allowed)})

    @app.exception_handler(RequestValidationError)
    async def readable_validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"])
            parts.append(f"{loc}: {err['msg']}")
        return JSONResponse({"detail": "; ".join(parts)}, 422)

    for module in (health, ingest, tasks, episodes, calibrations, alerts, keys, dashboard):
        app.include_router(module.router)
    app.openapi = lambda: openapi_with_errors(app)
    app.mount("/static", StaticFiles(directory=dashboard.STATIC_DIR), name="static")
    app.add_middleware(IngestFastPath)   # inside the body limit and the request timer
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(RequestTimer)
    return app
