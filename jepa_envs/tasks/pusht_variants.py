"""Which PushT ``gym.make`` builds: ``JEPA/PushT-v0`` takes ``variant=``.

- ``"embedded"`` (default): our T (bar 144 x 36), friction 1, difficulty presets (``easy`` default), success at
  coverage 0.80 on easy (``jepa_envs.tasks.pusht``; the CPU main job's task);
- ``"standard"``: gym-pusht 0.1.8's Push-T, the task Diffusion Policy and LeRobot publish numbers on
  (``jepa_envs.tasks.pusht_standard``); its own id ``JEPA/PushTStandard-v0`` and task name ``PushTStandard``.
"""
from __future__ import annotations

import numpy as np

from jepa_envs.tasks.pusht import WORLD_SIZE, PushTEnv
from jepa_envs.tasks.pusht_standard import PushTStandardEnv
from jepa_envs.tasks.spec import get_task_spec

VARIANTS = {"embedded": ("PushT", PushTEnv), "standard": ("PushTStandard", PushTStandardEnv)}


def make_pusht(task: str = "PushT", variant: str | None = None, **kwargs):
    """The PushT env of ``variant`` (default: the one ``task`` names, PushT -> embedded)."""
    if variant is not None and variant not in VARIANTS:
        raise ValueError(f"unknown PushT variant {variant!r}; known variants: embedded (default: our T, difficulty "
                         "presets easy/medium/hard/full), standard (gym-pusht 0.1.8's task, as Diffusion Policy and "
                         "LeRobot report it)")
    named = {name: v for v, (name, _) in VARIANTS.items()}
    if task not in named:
        raise ValueError(f"make_pusht builds the PushT tasks {sorted(named)}, not {task!r}")
    if variant is not None and named[task] != variant and task != "PushT":
        raise ValueError(f"task {task!r} is the {named[task]} PushT; variant={variant!r} asks for another one "
                         f"(use JEPA/PushT-v0 with variant={variant!r})")
    name, cls = VARIANTS[variant or named[task]]
    return cls(task=name, **kwargs)


def demonstration_mismatches(spec, image_shapes: dict, feature_names, action_ranges, state_ranges) -> list[str]:
    """How demonstrations for a PushT task do not match its variant, one phrase each (empty for other tasks).

    ``image_shapes``: the image features that fill the task's camera, with their [H, W, C]; ``feature_names``:
    every feature of the dataset; ``action_ranges`` / ``state_ranges``: per episode, the per-dimension (min, max)
    of the actions and of the agent positions, or None when the dataset does not say.

    Both variants act with absolute agent targets in table units (0-512), the units of the agent position, and
    the PD controller brings the agent to its targets within a few steps, so in an episode the agent's positions
    reach the range of its targets. Actions outside the table, or targets that in most episodes stay more than
    ``TARGET_GAP`` units away from every position the agent takes, are in other units (normalised, pixels, deltas).
    The standard variant observes gym-pusht's 96 x 96 frames.
    """
    if spec.name not in {name for name, _ in VARIANTS.values()}:
        return []
    problems = []
    standard_keys = set(get_task_spec("PushTStandard").extra["lerobot_image_keys"])
    if spec.name == "PushT" and standard_keys & set(feature_names):
        problems.append(f"the dataset is laid out as LeRobot's lerobot/pusht ({', '.join(sorted(standard_keys))}), "
                        "the standard PushT's data: pass --task PushTStandard (the embedded PushT is another T)")
    if spec.name == "PushTStandard":
        for key, shape in image_shapes.items():
            if list(shape)[:2] != [spec.image_size, spec.image_size]:
                problems.append(f"{key} is {shape[0]} x {shape[1]}; the standard PushT observes {spec.image_size} x "
                                f"{spec.image_size} frames (gym-pusht's, as in lerobot/pusht): record them at that "
                                "size")
    if action_ranges is None or state_ranges is None:
        problems.append("the dataset gives no per-episode min/max of its actions and agent positions (meta/episodes "
                        "stats), so their units cannot be checked; re-download its meta folder")
        return problems
    a_lo, a_hi = (np.asarray([r[i] for r in action_ranges], dtype=np.float64) for i in (0, 1))
    s_lo, s_hi = (np.asarray([r[i] for r in state_ranges], dtype=np.float64) for i in (0, 1))
    if a_lo.ndim != 2 or a_lo.shape != s_lo.shape:
        return problems   # not 2-D targets beside a 2-D agent position: the shape check has named that
    outside = a_lo.min() < -1.0 or a_hi.max() > WORLD_SIZE + 1.0
    gaps = np.maximum(np.maximum(a_lo - s_hi, s_lo - a_hi), 0.0).max(axis=1)   # per episode, worst dimension
    if outside or np.median(gaps) > TARGET_GAP:
        problems.append(f"actions span {_interval(a_lo.min(0), a_hi.max(0))} and agent positions "
                        f"{_interval(s_lo.min(0), s_hi.max(0))} (targets {np.median(gaps):.0f} units from the agent's "
                        f"path in the median episode); PushT acts with absolute agent targets in table units "
                        f"(0-{WORLD_SIZE:g}), the agent position's: convert the actions to table units")
    return problems


TARGET_GAP = 30.0   # table units; two agent radii


def _interval(lo: np.ndarray, hi: np.ndarray) -> str:
    return "[" + ", ".join(f"{a:.3g}..{b:.3g}" for a, b in zip(lo, hi)) + "]"
