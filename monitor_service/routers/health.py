"""Liveness, readiness and the Prometheus scrape endpoint."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST

from monitor_service.auth import Principal, require
from monitor_service.db import current_revision, head_revision
from monitor_service.metrics import exposition
from monitor_service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """The process is up (no database access, no key)."""
    return Health(status="ok")


@router.get("/readyz", response_model=Health, responses={503: {"model": Health}})
def readyz(request: Request):
    """Ready when the database answers and its schema is at the packaged head revision."""
    try:
        rev = current_revision(request.app.state.engine)
    except Exception as exc:  # any driver error means not ready; the message says which
        return JSONResponse(Health(status="unavailable", detail=f"database error: {exc}").model_dump(), 503)
    head = head_revision()
    if rev != head:
        return JSONResponse(
            Health(status="unavailable",
                   detail=f"schema at {rev}, needs {head}: run `jepa-monitor db upgrade`").model_dump(), 503
        )
    return Health(status="ok", detail=f"schema {rev}")


@router.get("/metrics", response_class=Response, responses={
    200: {"content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}},
          "description": "Prometheus text exposition"}})
async def metrics(request: Request, _: Principal = Depends(require("operator"))) -> Response:
    """Prometheus exposition (needs an operator key: configure the scrape job's bearer token)."""
    s = request.app.state.settings
    body = await run_in_threadpool(exposition, request.app.state.read_sessionmaker,
                                   (s.running_window, s.alert_debounce, s.alert_clear_ratio))
    return Response(body, media_type=CONTENT_TYPE_LATEST)
