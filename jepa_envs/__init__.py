"""Gymnasium environments for every task of the JEPA Policy paper behind one interface.

``import jepa_envs`` registers the ids; ``gym.make("JEPA/ToolHang-v0")`` then builds the task.
Backends are imported only when their env is made, so PushT works without robosuite or LIBERO.
"""
from __future__ import annotations

import gymnasium as gym

from jepa_envs.tasks.entry import creator
from jepa_envs.tasks.spec import TaskSpec, all_task_specs, get_task_spec, register_task

_ENTRY_POINTS = {
    "embedded": "jepa_envs.tasks.pusht_variants:make_pusht",   # variant="embedded" (default) or "standard"
    "robomimic": "jepa_envs.tasks.robomimic_env:RobomimicEnv",
    "libero": "jepa_envs.tasks.libero_env:LiberoEnv",
    "mimicgen": "jepa_envs.tasks.mimicgen_env:MimicGenEnv",
}


def _register_all() -> None:
    for spec in all_task_specs():
        if spec.suite not in _ENTRY_POINTS or spec.env_id in gym.registry:
            continue
        gym.register(
            id=spec.env_id,
            entry_point=creator(_ENTRY_POINTS[spec.suite]),
            max_episode_steps=spec.max_episode_steps,
            kwargs={"task": spec.name},
            disable_env_checker=True,
        )


_register_all()

from jepa_envs.real_robot.registration import register_real_robot_envs  # noqa: E402

register_real_robot_envs()

__all__ = ["TaskSpec", "get_task_spec", "all_task_specs", "register_task"]
