"""FastAPI dependencies: settings and one database session per request."""
from __future__ import annotations

from collections.abc import Iterator

from fastapi import Request
from sqlalchemy.orm import Session

from monitor_service.settings import MonitorSettings


def get_settings(request: Request) -> MonitorSettings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    """A writing session per request; handlers commit explicitly, so a 2xx means the record is committed."""
    with request.app.state.write_lock:
        session = request.app.state.sessionmaker()
        try:
            yield session
        finally:
            session.close()


def get_read_session(request: Request) -> Iterator[Session]:
    """A reading session per request (takes no write lock)."""
    session = request.app.state.read_sessionmaker()
    try:
        yield session
    finally:
        session.close()
