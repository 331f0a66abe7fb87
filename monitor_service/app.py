"""The FastAPI application factory."""
from __future__ import annotations

import asyncio
import contextlib
import threading
import time

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from monitor_service import db
from monitor_service.alerts import webhook_loop
from monitor_service.auth import ensure_admin_key
from monitor_service.metrics import REQUEST_SECONDS
from monitor_service.routers import alerts, calibrations, dashboard, episodes, health, ingest, keys, tasks
from monitor_service.settings import MonitorSettings


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


def create_app(settings: MonitorSettings | None = None) -> FastAPI:
    """Build the service: storage (migrated to head unless disabled), auth bootstrap, routers and background tasks."""
    settings = settings or MonitorSettings()
    engine = db.make_engine(settings.database_url)
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
        task = asyncio.create_task(webhook_loop(make_session, settings, app.state.stop)) if settings.webhook_urls else None
        try:
            yield
        finally:
            app.state.stop.set()
            if task is not None:
                await task
            engine.dispose()

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
    app.state.known_dims = {}  # task -> latent size, filled as ingestion meets tasks
    # SQLite has one writer; queueing writers of this process on a lock hands over at once, where SQLite's own
    # busy handler would sleep and poll (long tails). Other worker processes still queue on busy_timeout.
    app.state.write_lock = threading.Lock() if engine.dialect.name == "sqlite" else contextlib.nullcontext()
    app.state.stop = asyncio.Event()

    @app.exception_handler(RequestValidationError)
    async def readable_validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"])
            parts.append(f"{loc}: {err['msg']}")
        return JSONResponse({"detail": "; ".join(parts)}, 422)

    for module in (health, ingest, tasks, episodes, calibrations, alerts, keys, dashboard):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=dashboard.STATIC_DIR), name="static")
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(RequestTimer)
    return app
