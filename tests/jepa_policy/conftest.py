"""Fixtures shared by the jepa_policy tests."""
import pytest


@pytest.fixture(autouse=True, scope="module")
def _single_threaded(one_thread):
    """Every policy test runs with one intra-op thread (``one_thread`` in tests/conftest.py)."""
    yield
