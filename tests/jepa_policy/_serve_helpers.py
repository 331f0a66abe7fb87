"""Fixtures and helpers of the policy-server tests (test_serve*.py import them): one small trained checkpoint per
test session, servers started in this process on a free port, and openpi-style clients."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from websockets.sync.client import connect

from jepa_policy.cli import main as policy_main
from jepa_policy.policy import Policy
from jepa_policy.serve import PolicyServer, ServeConfig, unpack
from jepa_policy.serve.events import LOGGER

GOOD = {"top_image": np.zeros((32, 32, 3), np.uint8), "agent_pos": np.zeros(2, np.float32)}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, pusht_demo_file):
    """A 4-step PushT checkpoint at 32 px, trained once per session (the modules share it through the disk)."""
    out = tmp_path_factory.getbasetemp() / "serve-checkpoint"
    path = out / "checkpoints" / "latest.pt"
    if not path.is_file():
        assert policy_main(["train", "--task", "PushT", "--preset", "quick", "--dataset", str(pusht_demo_file),
                            "--steps", "4", "--warmup-steps", "1", "--eval-every", "0", "--out", str(out),
                            "--no-progress"]) == 0
    return path


@pytest.fixture
def serve(checkpoint):
    """Start servers of the checkpoint (``serve(max_queue=1, ...)``: ServeConfig's fields); stopped afterwards."""
    servers = []

    def start(**config) -> PolicyServer:
        policy = Policy.from_checkpoint(checkpoint)
        server = PolicyServer(policy, ServeConfig(port=config.pop("port", 0), **config), str(checkpoint))
        servers.append(server.start_in_thread())
        return server
    yield start
    for server in servers:
        server.stop()


@pytest.fixture
def unpaced(monkeypatch):
    """No pacing and no closing: a test that sends many bad requests in a row to read each refusal's message
    (pacing itself is tested on its own)."""
    import jepa_policy.serve.server as server_module
    monkeypatch.setattr(server_module, "PACE_FIRST_S", 0.0)
    monkeypatch.setattr(server_module, "PENALTY_CLOSE", float("inf"))
    monkeypatch.setattr(server_module, "REFUSED_RATE", float("inf"))


@pytest.fixture
def events(caplog):
    """A function that returns the server's event log so far, each line parsed (a dict)."""
    caplog.set_level(logging.INFO, logger=LOGGER)
    return lambda: [json.loads(r.getMessage()) for r in caplog.records if r.name == LOGGER]


def client(server: PolicyServer, headers=None, **kwargs):
    """An openpi-client-like connection (no compression, no size limit) and the metadata the server sent."""
    ws = connect(f"ws://127.0.0.1:{server.port}", compression=None, max_size=None, additional_headers=headers,
                 **kwargs)
    return ws, unpack(ws.recv())
