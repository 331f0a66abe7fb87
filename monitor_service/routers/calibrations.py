"""Per-task calibrations from held-out labelled episodes, and the report with its pooled-figure warning."""
from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select
from sqlalchemy.orm import Session

from monitor_service.auth import Principal, require
from monitor_service.db import CalibrationRow
from monitor_service.deps import get_read_session
from monitor_service.schemas import CalibrateIn, CalibrationOut, ObjectId, PooledWarning, ReportOut, errors
from monitor_service.service import calibrate_task, report

router = APIRouter(prefix="/v1", tags=["calibrations"])


def calibration_out(r: CalibrationRow) -> CalibrationOut:
    return CalibrationOut(
        id=r.id, task=r.task, checkpoint=r.checkpoint, active=r.active, rule=r.rule,
        threshold=r.threshold, auroc=r.auroc, result=r.result, created_at=r.created_at,
    )


@router.post("/calibrations", response_model=CalibrationOut, status_code=201, responses=errors(404, 409))
async def create_calibration(request: Request, body: CalibrateIn,
                             _: Principal = Depends(require("admin"))) -> CalibrationOut:
    """Calibrate a task (or one checkpoint of it) from its held-out labelled episodes and make it the active one:
    the alert rule's threshold (at most alpha of successful episodes alert), detection figures, controls."""
    app = request.app
    try:
        row = await run_in_threadpool(
            calibrate_task, app.state.sessionmaker, app.state.settings, body.task, body.checkpoint, body.alpha,
            body.rule, body.n_bootstrap, body.n_permutation, body.seed, body.folds, body.shape, body.signals,
            body.combination,
        )
    except LookupError as exc:
        raise HTTPException(404, str(exc)) from None
    except ValueError as exc:   # a valid request the stored episodes cannot support (too few, one class only)
        raise HTTPException(409, str(exc)) from None
    app.state.ingest.forget_calibrations()   # this process alerts with it from the next record on
    return calibration_out(row)


@router.get("/calibrations", response_model=list[CalibrationOut])
def list_calibrations(
    task: str | None = None, active: bool | None = None,
    session: Session = Depends(get_read_session), _: Principal = Depends(require("operator")),
) -> list[CalibrationOut]:
    """Calibrations, newest first."""
    q = select(CalibrationRow).order_by(CalibrationRow.id.desc())
    if task:
        q = q.where(CalibrationRow.task == task)
    if active is not None:
        q = q.where(CalibrationRow.active.is_(active))
    return [calibration_out(r) for r in session.scalars(q)]


@router.get("/calibrations/{calibration_id}", response_model=CalibrationOut, responses=errors(404))
def get_calibration(calibration_id: ObjectId, session: Session = Depends(get_read_session),
                    _: Principal = Depends(require("operator"))) -> CalibrationOut:
    row = session.get(CalibrationRow, calibration_id)
    if row is None:
        raise HTTPException(404, f"calibration {calibration_id} does not exist; list them with GET /v1/calibrations")
    return calibration_out(row)


@router.get("/report", response_model=ReportOut)
def get_report(session: Session = Depends(get_read_session), _: Principal = Depends(require("operator"))) -> ReportOut:
    """Per-task active calibrations; the pooled AUROC only as a labelled warning beside them."""
    rep = report(session)
    return ReportOut(
        tasks=[calibration_out(r) for r in rep["tasks"]],
        uncalibrated_tasks=rep["uncalibrated_tasks"],
        pooled=PooledWarning(**rep["pooled"]),
    )
