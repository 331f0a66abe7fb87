"""One robot's session on the policy server: its episode, frame history and the predictions awaiting their target."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Session:
    """One connection's episode: its frame history, step counter and the predictions awaiting their target.

    The history holds the ``obs_steps`` frames a decision reads, oldest first. As in-process ``Policy.act``, a
    history that lacks frames (an episode's first step, or a gap in the steps) repeats its oldest frame; ``real``
    counts the frames that are not such copies, so a reply says ``history_padded`` exactly when a decision read one.
    """

    id: str
    obs_steps: int
    peer: str = ""
    episode: str = ""
    episodes: int = 0
    requests: int = 0
    history: deque = field(default_factory=deque)
    real: int = 0                                    # frames of the history that are not padding copies
    step: int = -1                                   # episode step of the newest frame seen
    pending: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)   # target step -> (t, z_hat)
    previous_chunk: tuple[int, np.ndarray] | None = None   # (step, normalised chunk) of the last decision: STAC
    prev_total_ms: float | None = None
    penalty: float = 0.0                             # refused requests, halving every half-life (server pacing)
    penalty_at: float = 0.0

    def refused(self, now: float, half_life: float) -> float:
        """Count one refused request; returns the connection's penalty (older refusals count less)."""
        self.penalty = self.penalty * 0.5 ** ((now - self.penalty_at) / half_life) + 1.0
        self.penalty_at = now
        return self.penalty

    def new_episode(self, episode: str | None) -> None:
        self.episodes += 1
        self.episode = episode or f"{self.id}-{self.episodes}"
        self.history = deque(maxlen=self.obs_steps)
        self.real = 0
        self.step = -1
        self.pending = {}
        self.previous_chunk = None

    def feed(self, frames: list[dict], newest_step: int | None) -> tuple[list[tuple[int, dict]], bool]:
        """Add frames (newest last) to the history; returns their (step, frame) and whether the history now holds
        padding (fewer than ``obs_steps`` consecutive real frames: an episode's start, or a gap in the steps)."""
        newest = self.step + len(frames) if newest_step is None else newest_step
        steps = list(range(newest - len(frames) + 1, newest + 1))
        if steps[0] != self.step + 1 or len(frames) >= self.obs_steps:
            self.history.clear()   # a gap (or a full history sent): the history restarts from these frames
            self.real = 0
        for frame in frames:
            if not self.history:
                self.history.extend([frame] * (self.obs_steps - 1))
            self.history.append(frame)
            self.real = min(self.real + 1, self.obs_steps)
        self.step = newest
        return list(zip(steps, frames)), self.real < self.obs_steps
