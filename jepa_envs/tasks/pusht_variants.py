"""Which PushT ``gym.make`` builds: ``JEPA/PushT-v0`` takes ``variant=``.

- ``"embedded"`` (default): our T (bar 144 x 36), friction 1, difficulty presets (``easy`` default), success at
  coverage 0.80 on easy (``jepa_envs.tasks.pusht``; the CPU main job's task);
- ``"standard"``: gym-pusht 0.1.8's Push-T, the task Diffusion Policy and LeRobot publish numbers on
  (``jepa_envs.tasks.pusht_standard``); its own id ``JEPA/PushTStandard-v0`` and task name ``PushTStandard``.
"""
from __future__ import annotations

from jepa_envs.tasks.pusht import PushTEnv
from jepa_envs.tasks.pusht_standard import PushTStandardEnv

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
