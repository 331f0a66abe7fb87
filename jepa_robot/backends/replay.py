"""Dry-run backend: replays a recorded episode's observations through the full bridge and moves nothing.

Point it at an episode the bridge recorded (``<record_dir>/<task>/<episode_id>.json``) and run a policy against
it exactly as against the robot: same protocol, same safety rules (with the set-up's own limits when its config
is given), same per-episode record. The scene does not react to the policy's actions: observation ``s`` is the
recorded decision frame at or before step ``s``. What a dry run checks is everything but the physics: that the
policy process connects, keeps up with the control rate, sends actions of the right shape inside the limits,
and how far its actions are from the recorded ones (``info["recorded_action_error"]``, the largest absolute
difference of the step's action from the one executed in the recording).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from jepa_robot.backends.base import RobotBackend, StepResult
from jepa_robot.episodes import load_episode
from jepa_envs.tasks.spec import get_task_spec


def recorded_bounds(manifest: dict, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The action bounds the recorded episode ran under (the bridge stores them with every episode).

    A recording without them (made before they were stored) gets no default: a dry run must never run
    without limits, so it then needs the set-up file (``--config``) whose workspace applies.
    """
    client = manifest.get("manifest", {})
    safety = client.get("safety", {})
    for low, high in ((client.get("action_low"), client.get("action_high")),
                      (safety.get("action_low"), safety.get("action_high"))):
        if low is not None and high is not None:
            return np.asarray(low, np.float64), np.asarray(high, np.float64)
    raise ValueError(f"{path} does not say which action bounds its episode ran under (it was recorded before "
                     "bridges stored them); pass --config SETUP.toml with the robot's limits for this dry run")


class ReplayBackend(RobotBackend):
    """Serves a recorded episode; ``bounds`` and ``joint_count`` come from the real set-up when known."""

    success_source = "sim"   # the recording plays the simulator: its outcome ends the replay
    realtime = False

    def __init__(self, manifest_path: str | Path, bounds: tuple[np.ndarray, np.ndarray] | None = None,
                 joint_count: int | None = None, realtime: bool = False):
        manifest_path = Path(manifest_path)
        if not manifest_path.is_file():
            raise FileNotFoundError(f"episode manifest {manifest_path} not found; pass the .json the bridge wrote "
                                    "next to the episode's .h5 (in its --record-dir)")
        self.manifest, arrays = load_episode(manifest_path)
        self._steps = np.asarray(arrays["decision_steps"], np.int64)
        self._frames = {key[len("obs/"):]: value for key, value in arrays.items() if key.startswith("obs/")}
        if not self._frames or self._steps.size == 0:
            raise ValueError(f"{manifest_path} records no observations; record an episode with --record-dir first")
        self._executed = np.asarray(arrays["actions_executed"], np.float64)
        spec = get_task_spec(self.manifest["task"])
        first_image = self._frames[spec.image_keys[0]]
        self.task_spec = spec.with_image_size(int(first_image.shape[1]))
        self._length = int(self.manifest["steps"])
        self._success = bool(self.manifest.get("is_success", False))
        dim = self.task_spec.action_dim
        if bounds is None:
            bounds = recorded_bounds(self.manifest, manifest_path)
        self._low, self._high = (np.asarray(b, np.float64) for b in bounds)
        if self._low.shape != (dim,) or self._high.shape != (dim,) or not (
                np.all(np.isfinite(self._low)) and np.all(np.isfinite(self._high))):
            raise ValueError(f"the dry run's action bounds must be {dim} finite numbers each; got {self._low} and "
                             f"{self._high}; pass --config SETUP.toml with the robot's limits")
        self._joint_count = joint_count
        self.realtime = bool(realtime)
        self._step = 0

    @property
    def action_low(self) -> np.ndarray:
        return self._low

    @property
    def action_high(self) -> np.ndarray:
        return self._high

    @property
    def joint_count(self) -> int | None:
        return self._joint_count

    def _frame(self) -> dict[str, np.ndarray]:
        index = int(np.searchsorted(self._steps, self._step, side="right")) - 1
        return {key: value[max(index, 0)].copy() for key, value in self._frames.items()}

    def reset(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
        self._step = 0
        return self._frame(), {"replay_of": self.manifest.get("episode_id"), "is_success": False}

    def apply(self, action: np.ndarray) -> StepResult:
        self._step += 1
        done = self._step >= self._length
        info = {"is_success": done and self._success}
        if self._step <= len(self._executed) and np.all(np.isfinite(self._executed[self._step - 1])):
            info["recorded_action_error"] = float(np.max(np.abs(action - self._executed[self._step - 1])))
        return StepResult(None if self.realtime else self._frame(), 0.0, done and self._success,
                          done and not self._success, info)

    def observe(self) -> dict[str, np.ndarray]:
        return self._frame()

    def hold(self) -> None:
        """Nothing moves in a replay."""

    def home(self) -> None:
        """Nothing moves in a replay; the next reset starts it over."""
