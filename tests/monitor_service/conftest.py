"""Fixtures for the monitor tests: a migrated SQLite app in a temp dir and API keys per role."""
from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from monitor_testkit import ADMIN, make_settings, new_key

from monitor_service.app import create_app


@pytest.fixture
def settings(tmp_path):
    return make_settings(tmp_path)


@pytest.fixture
def client(settings):
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture
def admin():
    return {"X-API-Key": ADMIN}


@pytest.fixture
def robot(client):
    return new_key(client, "arm1-key", "robot", "arm1")


@pytest.fixture
def operator(client):
    return new_key(client, "op-key", "operator")
