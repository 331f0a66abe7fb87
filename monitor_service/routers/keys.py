"""API key management (admin)."""
from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Request
from sqlalchemy import select
from sqlalchemy.orm import Session

from monitor_service.auth import Principal, create_key, require, revoke
from monitor_service.db import ApiKey
from monitor_service.deps import get_read_session, get_session
from monitor_service.schemas import KeyCreated, KeyIn, KeyOut, ObjectId, errors

router = APIRouter(prefix="/v1/keys", tags=["keys"])


def key_out(k: ApiKey) -> dict:
    return dict(id=k.id, name=k.name, role=k.role, robot=k.robot, created_at=k.created_at, revoked_at=k.revoked_at)


@router.post("", response_model=KeyCreated, status_code=201, responses=errors(409))
def new_key(body: KeyIn, session: Session = Depends(get_session),
            _: Principal = Depends(require("admin"))) -> KeyCreated:
    """Create a key; the secret is in this response only."""
    try:
        row, secret = create_key(session, body.name, body.role, body.robot)
    except ValueError as exc:   # the schema admits only valid roles and robots, so this is a name in use
        raise HTTPException(409, str(exc)) from None
    session.commit()
    return KeyCreated(**key_out(row), key=secret)


@router.get("", response_model=list[KeyOut])
def list_keys(session: Session = Depends(get_read_session), _: Principal = Depends(require("admin"))) -> list[KeyOut]:
    return [KeyOut(**key_out(k)) for k in session.scalars(select(ApiKey).order_by(ApiKey.id))]


@router.delete("/{key_id}", response_model=KeyOut, responses=errors(404))
def revoke_key(request: Request, key_id: ObjectId, session: Session = Depends(get_session),
               _: Principal = Depends(require("admin"))) -> KeyOut:
    """Revoke a key; requests with it are refused from now on."""
    try:
        row = revoke(session, key_id)
    except LookupError as exc:
        raise HTTPException(404, f"{exc}; list keys with GET /v1/keys") from None
    session.commit()
    request.app.state.key_cache.clear()   # refused from this process's next request on
    return KeyOut(**key_out(row))
