"""Fixtures: simulated robot bridges on free loopback ports, proxy envs and operator clients, all closed after."""
from __future__ import annotations

import pytest

import jepa_envs  # noqa: F401
from jepa_robot.backends.sim import SimBackend
from jepa_robot.bridge import BridgeConfig, RobotBridge
from jepa_envs.real_robot.proxy import RealRobotEnv
from jepa_robot.safety import SafetyConfig
from jepa_robot.operator import OperatorClient

# generous timing for tests not about timing: the machine is shared and may stall threads for a while
RELAXED = {"link_timeout_s": 2.0, "command_deadline_s": 60.0}


class Robot:
    """Builds bridges, clients and operator handles; ``close`` tears down everything in reverse order."""

    def __init__(self, tmp_path):
        self.tmp_path = tmp_path
        self._closers: list = []

    def bridge(self, task: str = "PushT", chunk_budget: int | None = None, realtime: bool = False,
               success_source: str = "sim", image_size: int | None = None, camera_replicas: int = 1,
               backend=None, observe_only: bool = False, curve: dict | None = None, **safety) -> RobotBridge:
        backend = backend or SimBackend(task, image_size=image_size, realtime=realtime,
                                        success_source=success_source, camera_replicas=camera_replicas)
        config = BridgeConfig("tcp://127.0.0.1:*", "tcp://127.0.0.1:*", str(self.tmp_path / "episodes"),
                              chunk_budget, observe_only, **(curve or {}))
        bridge = RobotBridge(backend, SafetyConfig(**{**RELAXED, **safety}), config).start()
        self._closers.append(bridge.close)
        return bridge

    def client(self, bridge: RobotBridge, **kwargs) -> RealRobotEnv:
        env = RealRobotEnv(address=bridge.control_endpoint, timeout_s=20.0, **kwargs)
        self._closers.append(env.close)
        return env

    def operator(self, bridge: RobotBridge) -> OperatorClient:
        op = OperatorClient(bridge.operator_endpoint)
        self._closers.append(op.close)
        return op

    def close(self) -> None:
        for close in reversed(self._closers):
            close()


@pytest.fixture
def robot(tmp_path):
    r = Robot(tmp_path)
    yield r
    r.close()
