"""Simulated robot: serves any jepa_envs simulation task through the bridge.

It is the same environment ``gym.make`` builds in-process, so a seeded episode run through the bridge reaches
the same states as the one run directly. It never pretends to be hardware: ``success_source`` is "sim"
unless the operator-confirmation path is being rehearsed.
"""
from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np

import jepa_envs  # noqa: F401  (registers the gym ids)
from jepa_robot.backends.base import RobotBackend, StepResult
from jepa_envs.tasks.spec import get_task_spec


class SimBackend(RobotBackend):
    """Wraps ``gym.make(<task id>)``; simulation time only advances when an action is applied."""

    realtime = False

    def __init__(self, task: str, image_size: int | None = None, success_source: str = "sim",
                 realtime: bool = False, camera_replicas: int = 1, env_kwargs: dict | None = None):
        spec = get_task_spec(task)
        if spec.suite == "real":
            raise ValueError(f"task {spec.name!r} is a real-robot task; the sim backend serves simulation tasks "
                             "(PushT, Square, ToolHang, ...); use --backend arx5 for the robot")
        if success_source not in ("sim", "operator"):
            raise ValueError("success_source must be 'sim' or 'operator'")
        kwargs = dict(env_kwargs or {})
        if image_size is not None:
            kwargs["image_size"] = int(image_size)
        self.env = gym.make(spec.env_id, **kwargs)
        spec = self.env.unwrapped.task_spec
        if camera_replicas < 1:
            raise ValueError("camera_replicas must be >= 1")
        # benchmark aid: repeat each rendered camera under extra keys so the wire carries the real robot's
        # three-stream payload; the replicas are labelled as such in the spec and never used for learning
        self.camera_replicas = int(camera_replicas)
        self._replica_of = {f"{c}_replica{r}_image": f"{c}_image" for c in spec.cameras
                            for r in range(1, self.camera_replicas)}
        if self._replica_of:
            spec = replace(spec, cameras=spec.cameras + tuple(k[:-len("_image")] for k in self._replica_of),
                           notes=spec.notes + f"; served with {self.camera_replicas} replicas of each camera")
        self.task_spec = spec
        self.success_source = success_source
        self.realtime = bool(realtime)
        box = self.env.action_space
        if not isinstance(box, gym.spaces.Box) or box.shape != (self.task_spec.action_dim,):
            raise ValueError(f"task {spec.name} has action space {box}; the bridge drives Box actions of "
                             f"shape ({self.task_spec.action_dim},)")
        self._low = np.asarray(box.low, np.float64)
        self._high = np.asarray(box.high, np.float64)
        self._obs: dict[str, np.ndarray] | None = None

    @property
    def action_low(self) -> np.ndarray:
        return self._low

    @property
    def action_high(self) -> np.ndarray:
        return self._high

    def _with_replicas(self, obs: dict) -> dict:
        for key, source in self._replica_of.items():
            obs[key] = obs[source].copy()
        return obs

    def reset(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
        obs, info = self.env.reset(seed=seed)
        self._obs = obs = self._with_replicas(dict(obs))
        return obs, dict(info)

    def apply(self, action: np.ndarray) -> StepResult:
        obs, reward, terminated, truncated, info = self.env.step(action.astype(self.env.action_space.dtype))
        self._obs = obs = self._with_replicas(dict(obs))
        return StepResult(obs, float(reward), bool(terminated), bool(truncated), dict(info))

    def current_action(self) -> np.ndarray | None:
        """robosuite tasks: the absolute action that keeps every arm where it is (open gripper).

        Reading it changes nothing in the simulation (``controller_pose`` works on a copy of the state), so a
        seeded episode through the bridge reaches exactly the states it reaches in-process."""
        base = self.env.unwrapped
        if getattr(base, "action_mode", None) == "abs" and hasattr(base, "hold_action"):
            return np.asarray(base.hold_action(), np.float64)
        return None

    def joint_positions(self) -> np.ndarray | None:
        """robosuite tasks: the simulated arm joint angles, so joint limits are checked as on hardware."""
        robots = getattr(getattr(self.env.unwrapped, "backend", None), "robots", None)
        if not robots:
            return None
        return np.concatenate([np.asarray(r._joint_positions, np.float64) for r in robots])

    @property
    def joint_count(self) -> int | None:
        robots = getattr(getattr(self.env.unwrapped, "backend", None), "robots", None)
        if not robots:
            return None
        return sum(len(r.joint_indexes) for r in robots)

    def hold(self) -> None:
        """Nothing moves in a simulator between steps, so holding is not stepping."""

    def home(self) -> None:
        """A simulator is homed by its next reset; nothing moves until then."""

    def observe(self) -> dict[str, np.ndarray]:
        """The current observation; a simulator observed before any reset starts at seed 0 (observe-only mode)."""
        if self._obs is None:
            self.reset(0)
        return self._obs

    def set_render_images(self, enabled: bool) -> None:
        self.env.unwrapped.set_render_images(enabled)

    def close(self) -> None:
        self.env.close()
