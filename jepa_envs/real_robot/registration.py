"""Real-robot task specs and gym ids (Sec. 4.8); imports neither ZeroMQ nor any hardware SDK.

The hardware study: a two-arm ARX-5, three 128x128 RGB cameras, driver at 30 Hz, actions at 10 Hz, 8 actions
executed per chunk, a fixed per-task action-chunk budget, operator-confirmed success. The paper does not print
the budgets; ours (below) give each task 1.5-2x the length of a typical demonstration and are shared by every
policy evaluated on the task, which is the property the paper requires.
"""
from __future__ import annotations

import gymnasium as gym

from jepa_envs.tasks.entry import creator
from jepa_envs.tasks.spec import ABS_ACTION_DIM_PER_ARM, TaskSpec, arm_lowdim, register_task

REAL_CAMERAS = ("base", "left_wrist", "right_wrist")
REAL_IMAGE_SIZE = 128
REAL_CONTROL_HZ = 10.0
REAL_DRIVER_HZ = 30.0
REAL_N_ACTION_STEPS = 8
PROXY_ENTRY_POINT = "jepa_envs.real_robot.proxy:RealRobotEnv"

# name -> (arms used, action-chunk budget); one chunk = 8 actions = 0.8 s at 10 Hz
REAL_TASKS = {
    "Cabinet": (("left", "right"), 60),
    "CupStack": (("right",), 40),
    "CupUpright": (("right",), 30),
    "PlateGrape": (("left", "right"), 50),
    "PenInsert": (("right",), 40),
}


def real_task_spec(name: str, arms: tuple[str, ...], chunk_budget: int) -> TaskSpec:
    """TaskSpec of one real-robot task; robot0 is the first arm listed in ``arms`` (the right arm when alone)."""
    num_arms = len(arms)
    return TaskSpec(
        name=name, env_id=f"JEPA/RealRobot-{name}-v0", suite="real", source_task=f"arx5_{name.lower()}",
        cameras=REAL_CAMERAS, lowdim=arm_lowdim(num_arms), action_dim=ABS_ACTION_DIM_PER_ARM * num_arms,
        num_arms=num_arms, control_hz=REAL_CONTROL_HZ, horizon=16, future_k=4,
        max_episode_steps=chunk_budget * REAL_N_ACTION_STEPS, image_size=REAL_IMAGE_SIZE,
        n_action_steps=REAL_N_ACTION_STEPS, num_demos=100,
        notes="ARX-5 hardware through jepa-robot-bridge; success is confirmed by the operator",
        extra={"arms": arms, "chunk_budget": chunk_budget, "driver_hz": REAL_DRIVER_HZ},
    )


def register_real_robot_envs() -> None:
    """Register the five real-robot TaskSpecs, ``JEPA/RealRobot-v0`` and one id per task."""
    for name, (arms, budget) in REAL_TASKS.items():
        spec = register_task(real_task_spec(name, arms, budget))
        if spec.env_id not in gym.registry:
            # no TimeLimit: the bridge owns the chunk budget and ends the episode itself
            gym.register(id=spec.env_id, entry_point=creator(PROXY_ENTRY_POINT), kwargs={"task": name},
                         disable_env_checker=True)
    if "JEPA/RealRobot-v0" not in gym.registry:
        gym.register(id="JEPA/RealRobot-v0", entry_point=creator(PROXY_ENTRY_POINT), disable_env_checker=True)
