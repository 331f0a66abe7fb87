"""The observation/action convention shared by every backend.

Observations: a ``spaces.Dict`` with one ``uint8 (S, S, 3)`` Box per camera named ``<camera>_image`` and one
float32 Box per low-dim key of the task spec. ``info["is_success"]`` on every step.
Rendering can be switched off between the steps a consumer needs frames on (``set_render_images``); while it
is off the image entries are all-zero arrays of the declared shape and no camera is rendered.
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from jepa_envs.tasks.spec import TaskSpec


def observation_space_for(spec: TaskSpec) -> spaces.Dict:
    s = spec.image_size
    entries: dict[str, spaces.Space] = {
        key: spaces.Box(0, 255, shape=(s, s, 3), dtype=np.uint8) for key in spec.image_keys
    }
    for key, dim in spec.lowdim:
        entries[key] = spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float32)
    return spaces.Dict(entries)


class JEPAEnv(gym.Env):
    """Base class: spaces from the task spec, render-on-demand switch, success flag convention."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, spec: TaskSpec, render_mode: str | None = None):
        self.task_spec = spec
        self.render_mode = render_mode
        self.observation_space = observation_space_for(spec)
        self._render_images = True

    def set_render_images(self, enabled: bool) -> None:
        """Render camera images for the following steps (True) or leave them black (False)."""
        self._render_images = bool(enabled)

    @property
    def render_images(self) -> bool:
        return self._render_images

    def blank_images(self) -> dict[str, np.ndarray]:
        s = self.task_spec.image_size
        return {key: np.zeros((s, s, 3), dtype=np.uint8) for key in self.task_spec.image_keys}
