"""Hardware backends of the robot bridge: ``sim`` (any jepa_envs simulation task) and ``arx5`` (the real arms).

Backends are imported only when selected, so the ARX-5 SDK and RealSense are never needed for simulation.
"""
from __future__ import annotations

from jepa_robot.backends.base import BackendUnavailable, RobotBackend, StepResult

BACKENDS = ("sim", "arx5")

__all__ = ["BACKENDS", "BackendUnavailable", "RobotBackend", "StepResult"]
