"""Task registry: an admin registers each task before robots may report on it."""
from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Request
from sqlalchemy import select
from sqlalchemy.orm import Session

from monitor_service.auth import Principal, require
from monitor_service.db import Task
from monitor_service.deps import get_read_session, get_session
from monitor_service.schemas import RESERVED_SIGNALS, Name, TaskIn, TaskOut, errors

router = APIRouter(prefix="/v1/tasks", tags=["tasks"])


def _out(t: Task) -> TaskOut:
    return TaskOut(name=t.name, latent_dim=t.latent_dim, description=t.description, signals=t.signals or [],
                   created_at=t.created_at)


@router.put("/{name}", response_model=TaskOut, responses=errors(409, 422))
def put_task(request: Request, name: Name, body: TaskIn, session: Session = Depends(get_session),
             _: Principal = Depends(require("admin"))) -> TaskOut:
    """Register a task (or update its description, or add named signals); its latent dimension is fixed once
    set, and a signal once registered stays (its stored scores keep their meaning)."""
    own = [s for s in body.signals or [] if s in RESERVED_SIGNALS]
    if own:
        raise HTTPException(422, f"{own[0]} is the service's own signal (computed from the latents); register only "
                                 "the names of scores robots send")
    task = session.get(Task, name)
    if task is None:
        task = Task(name=name, latent_dim=body.latent_dim, description=body.description,
                    signals=sorted(set(body.signals or [])))
        session.add(task)
    else:
        if body.latent_dim is not None and task.latent_dim not in (None, body.latent_dim):
            raise HTTPException(409, f"task {name!r} already uses latent_dim {task.latent_dim}; register a new task "
                                     "name")
        task.latent_dim = body.latent_dim or task.latent_dim
        task.description = body.description or task.description
        if body.signals:
            task.signals = sorted(set(task.signals or []) | set(body.signals))
    session.commit()
    request.app.state.ingest.forget_tasks()   # this process accepts the new signals from the next record on
    return _out(task)


@router.get("", response_model=list[TaskOut])
def list_tasks(session: Session = Depends(get_read_session),
               _: Principal = Depends(require("operator"))) -> list[TaskOut]:
    """All registered tasks."""
    return [_out(t) for t in session.scalars(select(Task).order_by(Task.name))]
