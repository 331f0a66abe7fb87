"""Task specifications: everything the policy needs to know about a task, so it needs no per-task code.

Facts from the paper, Sec. 4.1 ("Tasks", "Timing") and SPEC.md section 2.
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field, replace

ARM_LOWDIM = (("eef_pos", 3), ("eef_quat", 4), ("gripper_qpos", 2))
ABS_ACTION_DIM_PER_ARM = 10  # position 3 + 6-D rotation 6 + gripper 1 (Sec. 4.1)


def arm_lowdim(num_arms: int) -> tuple[tuple[str, int], ...]:
    """robosuite-style proprioception keys (eef position, eef quaternion, gripper joints) for each arm."""
    return tuple((f"robot{i}_{name}", dim) for i in range(num_arms) for name, dim in ARM_LOWDIM)


class ObservationLayout:
    """Observation keys derived from ``cameras`` and ``lowdim``; shared by TaskSpec and the policy's ModelConfig."""

    cameras: tuple[str, ...]
    lowdim: tuple[tuple[str, int], ...]

    @property
    def image_keys(self) -> tuple[str, ...]:
        return tuple(f"{c}_image" for c in self.cameras)

    @property
    def lowdim_keys(self) -> tuple[str, ...]:
        return tuple(k for k, _ in self.lowdim)

    @property
    def lowdim_dim(self) -> int:
        return sum(d for _, d in self.lowdim)


@dataclass(frozen=True)
class TaskSpec(ObservationLayout):
    """One task of the toolkit. Reach it from an env as ``env.unwrapped.task_spec``."""

    name: str                      # short name used by CLIs and configs, e.g. "ToolHang"
    env_id: str                    # gymnasium id, e.g. "JEPA/ToolHang-v0"
    suite: str                     # "embedded" | "robomimic" | "libero" | "mimicgen" | "real"
    source_task: str               # the backend's own task name
    cameras: tuple[str, ...]       # observation key of camera c is f"{c}_image"
    lowdim: tuple[tuple[str, int], ...]  # (key, dim) in the order the policy concatenates them
    action_dim: int                # dimension of the absolute action the policy predicts
    num_arms: int
    control_hz: float
    horizon: int                   # H: actions predicted per chunk
    future_k: int                  # k: env steps from the newest observation frame to the future target
    max_episode_steps: int
    image_size: int = 84
    n_action_steps: int = 8        # actions executed per chunk before replanning
    obs_steps: int = 2             # observation history frames
    num_demos: int = 0             # demonstrations in the paper's dataset
    notes: str = ""
    extra: dict = field(default_factory=dict, compare=False, hash=False)

    def with_image_size(self, size: int) -> "TaskSpec":
        return replace(self, image_size=int(size))


_TASKS: dict[str, TaskSpec] = {}


def register_task(spec: TaskSpec) -> TaskSpec:
    _TASKS[spec.name] = spec
    return spec


def get_task_spec(name_or_id: str) -> TaskSpec:
    """Look a task up by short name ("ToolHang") or gym id ("JEPA/ToolHang-v0")."""
    for spec in _TASKS.values():
        if name_or_id in (spec.name, spec.env_id):
            return spec
    known = ", ".join(sorted(_TASKS))
    raise KeyError(f"unknown task {name_or_id!r}; known tasks: {known}")


def all_task_specs() -> list[TaskSpec]:
    return list(_TASKS.values())


# third-party package each suite needs, and our module that wraps it
BACKENDS = {
    "embedded": ("pymunk", "jepa_envs.tasks.pusht"),
    "robomimic": ("robosuite", "jepa_envs.tasks.robomimic_env"),
    "libero": ("libero", "jepa_envs.tasks.libero_env"),
    "mimicgen": ("mimicgen", "jepa_envs.tasks.mimicgen_env"),
    "real": ("zmq", "jepa_envs.real_robot.proxy"),
}


def backend_available(suite: str) -> tuple[bool, str]:
    """Whether a suite's backend can be imported here, and why not."""
    if suite not in BACKENDS:
        return False, f"no backend for suite {suite!r}"
    package, module = BACKENDS[suite]
    if importlib.util.find_spec(package) is None:
        return False, f"package {package!r} not installed"
    if importlib.util.find_spec(module) is None:
        return False, f"module {module} missing"
    return True, "ok"


def _robomimic(name, source, cameras, num_arms, max_steps):
    return TaskSpec(
        name=name, env_id=f"JEPA/{name}-v0", suite="robomimic", source_task=source, cameras=cameras,
        lowdim=arm_lowdim(num_arms), action_dim=ABS_ACTION_DIM_PER_ARM * num_arms, num_arms=num_arms,
        control_hz=20.0, horizon=10, future_k=4, max_episode_steps=max_steps, num_demos=200,
    )


def _mimicgen(name, source, max_steps):
    return TaskSpec(
        name=name, env_id=f"JEPA/{name}-v0", suite="mimicgen", source_task=source,
        cameras=("agentview", "robot0_eye_in_hand"), lowdim=arm_lowdim(1), action_dim=10, num_arms=1,
        control_hz=20.0, horizon=10, future_k=4, max_episode_steps=max_steps, num_demos=1000,
    )


def _libero(name, source, max_steps):
    return TaskSpec(
        name=name, env_id=f"JEPA/{name}-v0", suite="libero", source_task=source,
        cameras=("agentview", "robot0_eye_in_hand"), lowdim=arm_lowdim(1), action_dim=10, num_arms=1,
        control_hz=20.0, horizon=16, future_k=4, max_episode_steps=max_steps, num_demos=50,
        notes="LIBERO data is 128x128; pass image_size=128 for LIBERO-native resolution",
    )


PUSHT = register_task(TaskSpec(
    name="PushT", env_id="JEPA/PushT-v0", suite="embedded", source_task="pusht",
    cameras=("top",), lowdim=(("agent_pos", 2),), action_dim=2, num_arms=0,
    control_hz=10.0, horizon=16, future_k=4, max_episode_steps=300, image_size=84, num_demos=0,
    notes="2-D pushing on pymunk; action = absolute target position of the round agent",
))
PUSHT_STANDARD = register_task(TaskSpec(
    name="PushTStandard", env_id="JEPA/PushTStandard-v0", suite="embedded", source_task="gym_pusht/PushT-v0",
    cameras=("top",), lowdim=(("agent_pos", 2),), action_dim=2, num_arms=0,
    control_hz=10.0, horizon=16, future_k=4, max_episode_steps=300, image_size=96, num_demos=206,
    notes="gym-pusht 0.1.8's Push-T (Diffusion Policy; LeRobot's lerobot/pusht, 206 demos): T of scale 30, "
          "success at coverage > 0.95; also gym.make('JEPA/PushT-v0', variant='standard')",
    # LeRobot's lerobot/pusht names its single camera observation.image (no .images.<name>), and its task so
    extra={"lerobot_image_keys": {"observation.image": "top_image"},
           "lerobot_task": "Push the T-shaped block onto the T-shaped target."},
))
register_task(_robomimic("Lift", "Lift", ("agentview", "robot0_eye_in_hand"), 1, 400))
register_task(_robomimic("Can", "PickPlaceCan", ("agentview", "robot0_eye_in_hand"), 1, 400))
register_task(_robomimic("Square", "NutAssemblySquare", ("agentview", "robot0_eye_in_hand"), 1, 400))
register_task(_robomimic("ToolHang", "ToolHang", ("sideview", "robot0_eye_in_hand"), 1, 700))
register_task(_robomimic(
    "Transport", "TwoArmTransport",
    ("shouldercamera0", "shouldercamera1", "robot0_eye_in_hand", "robot1_eye_in_hand"), 2, 700))
register_task(_libero("MokaMoka", "KITCHEN_SCENE8_put_both_moka_pots_on_the_stove", 600))
register_task(_libero(
    "MugMug",
    "LIVING_ROOM_SCENE5_put_the_white_mug_on_the_left_plate_and_put_the_yellow_and_white_mug_on_the_right_plate",
    300))
register_task(_mimicgen("CoffeePreparation", "CoffeePreparation_D1", 800))
register_task(_mimicgen("Kitchen", "Kitchen_D1", 800))
register_task(_mimicgen("ThreePieceAssembly", "ThreePieceAssembly_D1", 500))
register_task(_mimicgen("HammerCleanup", "HammerCleanup_D1", 500))
