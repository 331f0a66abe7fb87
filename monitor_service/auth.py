"""API keys with roles: robot (write its own robot's data, nothing else), operator (read, acknowledge),
admin (configure: tasks, keys, calibrations; read). Ingest is the robot role's alone: calibration data must
come from a robot, so neither an operator nor an admin key can write decisions, targets or outcomes."""
from __future__ import annotations

import hashlib
import secrets
import time
from dataclasses import dataclass

from fastapi import HTTPException, Request
from sqlalchemy import select
from sqlalchemy.orm import Session

from monitor_service.db import ApiKey, utcnow

ROLE_RANK = {"robot": 0, "operator": 1, "admin": 2}


@dataclass(frozen=True)
class Principal:
    """The authenticated caller of a request."""

    key_id: int
    name: str
    role: str
    robot: str | None


def hash_key(key: str) -> str:
    """Keys are stored as SHA-256 digests; the secret itself is shown only once."""
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> str:
    return "jm_" + secrets.token_urlsafe(32)


def create_key(session: Session, name: str, role: str, robot: str | None = None,
               key: str | None = None) -> tuple[ApiKey, str]:
    """Insert a key (random unless given) and return the row and the secret."""
    if role not in ROLE_RANK:
        raise ValueError(f"role {role!r} is unknown; use one of {sorted(ROLE_RANK)}")
    if role == "robot" and not robot:
        raise ValueError("a robot key needs the robot name it may write for (robot=...)")
    if session.scalar(select(ApiKey).where(ApiKey.name == name)) is not None:
        raise ValueError(f"a key named {name!r} exists already; pick another name or revoke it first")
    secret = key or new_key()
    row = ApiKey(name=name, key_hash=hash_key(secret), role=role, robot=robot if role == "robot" else None)
    session.add(row)
    session.flush()
    return row, secret


def ensure_admin_key(session: Session, key: str) -> None:
    """Bootstrap: make sure ``key`` is a valid admin key (used with JEPA_MONITOR_ADMIN_KEY)."""
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    if row is None:
        name = "bootstrap-admin"
        suffix = 1
        while session.scalar(select(ApiKey).where(ApiKey.name == name)) is not None:
            suffix += 1
            name = f"bootstrap-admin-{suffix}"
        create_key(session, name, "admin", key=key)
    elif row.role != "admin" or row.revoked_at is not None:
        raise ValueError("JEPA_MONITOR_ADMIN_KEY matches a revoked or non-admin key; choose a fresh secret")


def _presented_key(request: Request) -> str | None:
    key = request.headers.get("x-api-key")
    if key:
        return key
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return None


class KeyCache:
    """Known keys by hash for ``ttl_s`` seconds: a request is not a database query for its key. A revocation
    through this process clears the cache at once; another process's takes effect within ``ttl_s``."""

    def __init__(self, ttl_s: float = 2.0):
        self.ttl_s = ttl_s
        self.rows: dict[str, tuple[float, ApiKey]] = {}

    def lookup(self, make_session, key_hash: str) -> ApiKey | None:
        hit = self.rows.get(key_hash)
        now = time.monotonic()
        if hit is not None and now - hit[0] < self.ttl_s:
            return hit[1]
        # A short session of its own: the handler's transaction (a write lock on SQLite) starts only after auth.
        with make_session() as session:
            row = session.scalar(select(ApiKey).where(ApiKey.key_hash == key_hash))
            if row is not None:
                session.expunge(row)
        if row is not None:
            self.rows[key_hash] = (now, row)
        return row

    def clear(self) -> None:
        self.rows.clear()


def authenticate(request: Request, role: str, exact: bool = False) -> Principal:
    """The caller, who must hold ``role`` or a higher one (``exact``: that role only); 401 / 403 otherwise.

    Keys come from the app's KeyCache, so this runs on the event loop (a cache miss is one indexed query)."""
    key = _presented_key(request)
    if not key:
        raise HTTPException(401, "no API key: send it in the X-API-Key header (or Authorization: Bearer)")
    row = request.app.state.key_cache.lookup(request.app.state.read_sessionmaker, hash_key(key))
    if row is None or row.revoked_at is not None:
        raise HTTPException(401, "API key unknown or revoked: ask an admin for a key (jepa-monitor keys create)")
    if (row.role != role) if exact else (ROLE_RANK[row.role] < ROLE_RANK[role]):
        fix = ("ingestion is for robot keys only, each bound to its robot: create one with "
               "`jepa-monitor keys create --role robot --robot NAME`" if role == "robot" else
               f"this endpoint needs the {role!r} role")
        raise HTTPException(403, f"{fix}; your key {row.name!r} is {row.role!r}")
    return Principal(row.id, row.name, row.role, row.robot)


def require(role: str, exact: bool = False):
    """FastAPI dependency factory of :func:`authenticate` (async: no thread-pool hop per request)."""

    async def dependency(request: Request) -> Principal:
        return authenticate(request, role, exact)

    return dependency


def revoke(session: Session, key_id: int) -> ApiKey:
    """Revoke key ``key_id`` (again is fine); LookupError when there is none (the caller names how to list them)."""
    row = session.get(ApiKey, key_id)
    if row is None:
        raise LookupError(f"API key id {key_id} does not exist")
    row.revoked_at = row.revoked_at or utcnow()
    return row
