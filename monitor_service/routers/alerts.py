"""Alerts: list, acknowledge, and a server-sent-event stream of newly raised alerts."""
from __future__ import annotations

import asyncio
import json
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from monitor_service.alerts import alert_payload
from monitor_service.auth import Principal, require
from monitor_service.db import Alert, utcnow
from monitor_service.deps import get_read_session, get_session
from monitor_service.schemas import AckIn, AlertOut, MAX_ID, ObjectId, errors

router = APIRouter(prefix="/v1/alerts", tags=["alerts"])


def alert_out(a: Alert) -> AlertOut:
    return AlertOut(
        id=a.id, episode_id=a.episode_id, task=a.task, robot=a.robot, step=a.step, score=a.score,
        threshold=a.threshold, calibration_id=a.calibration_id, state=a.state, acknowledged_by=a.acknowledged_by,
        acknowledged_at=a.acknowledged_at, note=a.note, raised_at=a.raised_at, cleared_at=a.cleared_at,
        resolved_at=a.resolved_at, resolution=a.resolution, beyond_calibration=a.beyond_calibration,
        signals=a.signals, no_promise=bool(a.no_promise),
    )


@router.get("", response_model=list[AlertOut])
def list_alerts(
    state: Literal["open", "acknowledged", "cleared", "resolved"] | None = Query(
        None, description="open, acknowledged, cleared or resolved (docs/monitor.md, 'Alert life cycle')"),
    acknowledged: bool | None = None,
    task: str | None = None,
    limit: int = Query(200, ge=1, le=5000),
    session: Session = Depends(get_read_session),
    _: Principal = Depends(require("operator")),
) -> list[AlertOut]:
    """Alerts, newest first."""
    q = select(Alert).order_by(Alert.id.desc())
    if state:
        q = q.where(Alert.state == state)
    if acknowledged is not None:
        q = q.where(Alert.acknowledged_at.is_not(None) if acknowledged else Alert.acknowledged_at.is_(None))
    if task:
        q = q.where(Alert.task == task)
    return [alert_out(a) for a in session.scalars(q.limit(limit))]


@router.post("/{alert_id}/ack", response_model=AlertOut, responses=errors(404, 409))
def acknowledge(
    alert_id: ObjectId, body: AckIn | None = None, session: Session = Depends(get_session),
    principal: Principal = Depends(require("operator")),
) -> AlertOut:
    """An operator takes an open alert (it becomes acknowledged); acknowledging twice keeps the first operator
    and time. A cleared or resolved alert needs no one: 409."""
    alert = session.get(Alert, alert_id)
    if alert is None:
        raise HTTPException(404, f"alert {alert_id} does not exist; list alerts with GET /v1/alerts")
    if alert.state in ("cleared", "resolved"):
        raise HTTPException(409, f"alert {alert_id} is {alert.state} ("
                            + ("its statistic fell back below the hysteresis level" if alert.state == "cleared"
                               else f"its episode ended in {alert.resolution}") + "); there is nothing to acknowledge")
    if alert.acknowledged_at is None:
        alert.acknowledged_at = utcnow()
        alert.acknowledged_by = principal.name
        alert.state = "acknowledged"
        alert.note = (body.note if body else "") or alert.note
    session.commit()
    return alert_out(alert)


def _new_alerts(make_session, after: int) -> list[dict]:
    with make_session() as session:
        rows = session.scalars(select(Alert).where(Alert.id > after).order_by(Alert.id).limit(100)).all()
        out = [alert_payload(a) for a in rows]
        session.rollback()
    return out


def _max_alert_id(make_session) -> int:
    with make_session() as session:
        value = session.scalar(select(func.max(Alert.id))) or 0
        session.rollback()
    return value


@router.get("/stream", response_class=StreamingResponse, responses={
    200: {"content": {"text/event-stream": {"schema": {"type": "string"}}}, "description": "alert events"},
    **errors(400)})
async def stream(request: Request, _: Principal = Depends(require("operator"))) -> StreamingResponse:
    """Server-sent events: one `alert` event per newly raised alert; resumes after the Last-Event-ID header.

    The stream polls the database, so it sees alerts raised by every worker and survives restarts.
    """
    make_session = request.app.state.read_sessionmaker
    poll = request.app.state.settings.sse_poll_s
    stop: asyncio.Event = request.app.state.stop
    last = request.headers.get("last-event-id")
    if last is not None and not (last.isdigit() and int(last) <= MAX_ID):
        raise HTTPException(400, f"Last-Event-ID must be an alert id (0 to {MAX_ID}); got {last[:40]!r}")
    start = int(last) if last is not None else await run_in_threadpool(_max_alert_id, make_session)

    async def events():
        after = start
        idle = 0.0
        yield "retry: 1000\n\n"
        while not stop.is_set() and not await request.is_disconnected():
            for payload in await run_in_threadpool(_new_alerts, make_session, after):
                after = payload["id"]
                yield f"id: {after}\nevent: alert\ndata: {json.dumps(payload)}\n\n"
                idle = 0.0
            await asyncio.sleep(poll)
            idle += poll
            if idle >= 15.0:
                idle = 0.0
                yield ": keep-alive\n\n"

    return StreamingResponse(events(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})
