"""Wrappers for every JEPA backend: render cameras only when a chunked policy needs them, record videos.

Render-on-demand schedule (``RenderOnDemand``). Frame j is the observation after the j-th env step (frame 0 is
the reset observation). A chunked policy decides at frames 0, n, 2n, ... (n = ``decision_every``, the actions
executed per chunk) from the ``obs_steps`` newest frames, and the monitor compares the prediction made at
decision frame t with frame t + k (k = ``future_k``). So frame j is rendered exactly when

- j mod n is 0, n-1, ..., n-(obs_steps-1)  (the history frames of a decision; j = 0 is always rendered), or
- j >= k and (j - k) mod n == 0            (the future frame of the decision k steps earlier).

With the paper's n = 8, obs_steps = 2, k = 4 that is frames {0, 4, 7, 8, 12, 15, 16, ...}: 3 of every 8 steps.
All other steps return all-zero images (``JEPAEnv.set_render_images(False)``). ``info["images_rendered"]`` says
which kind a step returned.
"""
from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np


def frames_to_render(j: int, decision_every: int, obs_steps: int, future_k: int | None) -> bool:
    """Whether frame ``j`` is consumed by a chunked policy loop (see the module docstring)."""
    n = decision_every
    if (-j) % n < obs_steps:  # j is one of the obs_steps frames ending at a decision frame
        return True
    return bool(future_k) and j >= future_k and (j - future_k) % n == 0


def render_schedule(num_frames: int, decision_every: int, obs_steps: int, future_k: int | None) -> list[int]:
    """The frame indices in [0, num_frames) that ``RenderOnDemand`` renders."""
    return [j for j in range(num_frames) if frames_to_render(j, decision_every, obs_steps, future_k)]


class RenderOnDemand(gym.Wrapper):
    """Render camera images only on the steps a chunked policy loop and its monitor consume.

    Defaults come from the task spec (``n_action_steps``, ``obs_steps``, ``future_k``); pass ``future_k=0`` when
    no monitor needs future frames. Works with every backend: it only calls ``env.unwrapped.set_render_images``.
    """

    def __init__(self, env: gym.Env, decision_every: int | None = None, obs_steps: int | None = None,
                 future_k: int | None = None):
        super().__init__(env)
        base = env.unwrapped
        if not hasattr(base, "set_render_images") or not hasattr(base, "task_spec"):
            raise TypeError(f"RenderOnDemand needs a jepa_envs env (with set_render_images and task_spec); "
                            f"got {type(base).__name__}")
        spec = base.task_spec
        self.decision_every = int(decision_every if decision_every is not None else spec.n_action_steps)
        self.obs_steps = int(obs_steps if obs_steps is not None else spec.obs_steps)
        self.future_k = int(future_k if future_k is not None else spec.future_k)
        if self.decision_every < 1 or self.obs_steps < 1 or self.future_k < 0:
            raise ValueError("decision_every and obs_steps must be >= 1 and future_k >= 0; got "
                             f"{self.decision_every}, {self.obs_steps}, {self.future_k}")
        self.frame = 0

    def needs_render(self, frame: int) -> bool:
        return frames_to_render(frame, self.decision_every, self.obs_steps, self.future_k)

    def reset(self, **kwargs):
        self.frame = 0
        self.env.unwrapped.set_render_images(True)
        obs, info = self.env.reset(**kwargs)
        info["images_rendered"] = True
        return obs, info

    def step(self, action):
        self.frame += 1
        rendered = self.needs_render(self.frame)
        self.env.unwrapped.set_render_images(rendered)
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["images_rendered"] = rendered
        return obs, reward, terminated, truncated, info


class RecordEpisodeVideo(gym.Wrapper):
    """Write one video per episode (``<video_dir>/<name_prefix>-<n>.<format>``) from the env's frames.

    ``source="obs"`` records the camera images of the observations side by side (skipping steps whose images
    were not rendered, e.g. under ``RenderOnDemand``); ``source="render"`` records ``env.render()`` frames
    (needs ``render_mode="rgb_array"``). ``format`` "gif" needs only Pillow; "mp4" needs the imageio-ffmpeg
    package. The video is written when the episode ends, on the next reset, or on close.
    """

    def __init__(self, env: gym.Env, video_dir, name_prefix: str = "episode", format: str = "gif",
                 fps: float | None = None, source: str = "obs"):
        super().__init__(env)
        if format not in ("gif", "mp4"):
            raise ValueError(f"format must be 'gif' or 'mp4', got {format!r}")
        if format == "mp4":
            try:
                import imageio_ffmpeg  # noqa: F401
            except ImportError as exc:
                raise ImportError("mp4 videos need the imageio-ffmpeg package: pip install imageio-ffmpeg "
                                  "(or use format='gif')") from exc
        if source not in ("obs", "render"):
            raise ValueError(f"source must be 'obs' or 'render', got {source!r}")
        if source == "render" and env.render_mode != "rgb_array":
            raise ValueError("source='render' needs an env made with render_mode='rgb_array'")
        self.video_dir = Path(video_dir)
        self.video_dir.mkdir(parents=True, exist_ok=True)
        self.name_prefix, self.format, self.source = name_prefix, format, source
        self.fps = float(fps or env.metadata.get("render_fps", 10))
        self.episode = 0
        self.frames: list[np.ndarray] = []
        self.paths: list[Path] = []
        self._image_keys = env.unwrapped.task_spec.image_keys if source == "obs" else ()

    def _capture(self, obs) -> None:
        if self.source == "render":
            self.frames.append(np.asarray(self.env.render()))
            return
        images = [obs[k] for k in self._image_keys]
        if any(im.any() for im in images):
            self.frames.append(np.concatenate(images, axis=1))

    def _flush(self) -> None:
        if not self.frames:
            return
        path = self.video_dir / f"{self.name_prefix}-{self.episode}.{self.format}"
        if self.format == "gif":
            imageio.mimsave(path, self.frames, duration=1000.0 / self.fps, loop=0)
        else:
            imageio.mimsave(path, self.frames, fps=self.fps, macro_block_size=1)
        self.paths.append(path)
        self.frames = []
        self.episode += 1

    def reset(self, **kwargs):
        self._flush()
        obs, info = self.env.reset(**kwargs)
        self._capture(obs)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._capture(obs)
        if terminated or truncated:
            self._flush()
        return obs, reward, terminated, truncated, info

    def close(self):
        self._flush()
        super().close()
