"""Image faults on recorded frames: a dataset's observations shown as a fault (``jepa_envs.tasks.faults``) shows a
live episode's, through the fault's own wrapper, without the simulator (``jepa-policy audit --kind visibility``).

``FrameReplay`` plays recorded observations back as an episode; ``fault_frames`` wraps it in an image fault
(``IMAGE_FAULTS``: those that change camera images only) and returns what the fault shows, equal frame for frame to
a live faulted episode of the same seed and a fixed onset (tests/jepa_envs/tasks/test_faults.py).
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from jepa_envs.tasks.faults import FAULTS, FaultWrapper, wrap_fault


class FrameReplay(gym.Env):
    """Recorded observations played back as an episode: ``reset`` returns ``frames[0]``, the i-th ``step`` (any
    action) ``frames[i]``, and the last one terminates. Wrapped in an image fault (``IMAGE_FAULTS``), it shows
    the recorded frames as that fault shows a live episode's, with the same onset contract and per-seed draws:
    how a fault looks on a dataset's frames without the simulator (``jepa-policy audit --kind visibility``).
    ``spec``: the task the frames come from (its image keys, and whether PushT rendered them: its plain
    background is what ``BackgroundTint`` recolours)."""

    metadata: dict = {"render_modes": []}

    def __init__(self, spec, frames: list[dict]):
        if not frames:
            raise ValueError("FrameReplay needs at least one recorded frame")
        missing = [k for k in spec.image_keys if k not in frames[0]]
        if missing:
            raise KeyError(f"the recorded frames lack {missing}; the task {spec.name} has cameras {spec.image_keys}")
        self.task_spec, self.frames, self.i = spec, frames, 0
        self.plain_background = spec.name == "PushT"   # PushTEnv rendered them (its plain_background)
        first = frames[0]
        self.observation_space = gym.spaces.Dict({k: gym.spaces.Box(0, 255, np.shape(first[k]), np.uint8)
                                                  for k in spec.image_keys})
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (spec.action_dim,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.i = 0
        return dict(self.frames[0]), {}

    def step(self, action):
        if self.i + 1 >= len(self.frames):
            raise RuntimeError(f"FrameReplay has only {len(self.frames)} frames; reset it to play them again")
        self.i += 1
        return dict(self.frames[self.i]), 0.0, self.i + 1 == len(self.frames), False, {}


def _image_only(cls: type) -> bool:
    """A fault that changes only camera images: its effect can be applied to recorded frames. Read from which
    methods it overrides; an image fault whose ``image`` read the simulator's state would pass this check and must
    not be added to ``FAULTS`` without a replay test (tests/jepa_envs/tasks/test_faults.py)."""
    return (cls.image is not FaultWrapper.image and cls.begin is FaultWrapper.begin
            and cls.action is FaultWrapper.action and cls.step is FaultWrapper.step)


def fault_frames(spec, frames: list[dict], fault: str, seed: int, first_step: int = 1, **kwargs) -> list[dict]:
    """``frames`` (recorded observations of task ``spec``, in time order, ``frames[0]`` that of env step
    ``first_step``) as an image fault with its onset fixed at ``first_step - 1`` shows them: the same images a live
    episode with that fixed onset, reset with ``seed``, shows at those steps (the fault's per-episode draws, the
    shift's direction or the distractors' places, come from the seed; ``sensor_noise``'s from the step). A live
    episode whose onset is drawn from a range spends a draw on the onset first, so its draws differ from these
    (they follow the same law). ``kwargs``: the fault's options. Refuses faults that change the simulation or the
    actions (they need a live env)."""
    if fault not in FAULTS:
        raise ValueError(f"unknown fault {fault!r}; choose one of {sorted(FAULTS)}")
    if fault not in IMAGE_FAULTS:
        raise ValueError(f"{fault} changes the {FAULTS[fault].kind} of a live episode, not recorded frames; image "
                         f"faults are {IMAGE_FAULTS} (measure {fault} with jepa-policy eval --faults)")
    if "onset" in kwargs:
        raise ValueError(f"fault_frames sets {fault}'s onset itself (first_step - 1, before the first frame); drop "
                         "onset= from its options")
    if first_step < 1:
        raise ValueError(f"first_step must be >= 1 (the onset is first_step - 1), got first_step={first_step}")
    env = wrap_fault(FrameReplay(spec, [frames[0]] * first_step + list(frames)), fault, onset=first_step - 1,
                     **kwargs)
    env.reset(seed=seed)
    no_action = np.zeros(spec.action_dim, np.float32)
    shown = [env.step(no_action)[0] for _ in range(first_step - 1 + len(frames))]
    return shown[first_step - 1:]


IMAGE_FAULTS = sorted(name for name, info in FAULTS.items() if _image_only(info.wrapper))
