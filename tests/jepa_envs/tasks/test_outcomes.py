"""Each kind of pick failure, produced in the real simulator and named from its state (jepa_envs/tasks/outcomes.py):
the scripted expert drives Lift and Can to the state (a grasp, a lift, a release), a direct state change knocks
the object away, and the gripper pressed onto the table gets stuck; the env reports the kind every step."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import jepa_envs  # noqa: F401
from jepa_envs.tasks.outcomes import FAILURE_KINDS, KNOCKED_M, failure_kind_name
from jepa_envs.tasks.robosuite_expert import expert_for

pytestmark = pytest.mark.timeout(300)


def _kind(info) -> str:
    return failure_kind_name(info["failure_kind"])


def _run_expert_until(env, task: str, seed: int, stop_phase: str, extra_steps: int = 0):
    """Step the expert from a reset until it enters ``stop_phase`` (plus ``extra_steps``); the last info."""
    expert = expert_for(task, seed=seed)
    obs, info = env.reset(seed=seed)
    expert.reset(env)
    for _ in range(400):
        action = expert.act(env)
        if expert.phase == stop_phase:
            for _ in range(extra_steps):
                obs, _, _, _, info = env.step(action)
            return action, info
        obs, _, terminated, _, info = env.step(action)
        assert not terminated, f"the episode succeeded before phase {stop_phase}"
    raise AssertionError(f"the expert never reached phase {stop_phase}")


@pytest.fixture(scope="module")
def lift():
    env = gym.make("JEPA/Lift-v0", image_size=32)
    env.unwrapped.set_render_images(False)
    yield env
    env.close()


@pytest.fixture(scope="module")
def can():
    env = gym.make("JEPA/Can-v0", image_size=32)
    env.unwrapped.set_render_images(False)
    yield env
    env.close()


def test_a_still_robot_never_grasped_and_a_success_is_none(lift):
    _, info = lift.reset(seed=1)
    for _ in range(20):
        *_, info = lift.step(lift.unwrapped.hold_action())
    assert _kind(info) == "never_grasped"
    expert = expert_for("Lift", seed=1)
    lift.reset(seed=1)
    expert.reset(lift)
    for _ in range(400):
        *_, terminated, _, info = lift.step(expert.act(lift))
        if terminated:
            break
    assert terminated and info["is_success"] and _kind(info) == "none"


def test_held_on_the_table_then_dropped(lift):
    action, info = _run_expert_until(lift, "Lift", seed=2, stop_phase="lift")
    assert _kind(info) == "held_not_lifted", "closed on the cube, not lifted yet"
    opened = action.copy()
    opened[-1] = -1.0   # open the gripper where it is
    for _ in range(15):
        *_, info = lift.step(opened)
    assert _kind(info) == "dropped"


def test_can_lifted_but_not_placed_is_lifted_timeout_and_dropped_on_release(can):
    action, info = _run_expert_until(can, "Can", seed=3, stop_phase="carry", extra_steps=5)
    assert _kind(info) == "lifted_timeout"
    opened = action.copy()
    opened[-1] = -1.0
    for _ in range(25):
        *_, info = can.step(opened)
    assert _kind(info) == "dropped"


def test_an_object_moved_without_a_grasp_is_knocked_away(lift):
    _, info = lift.reset(seed=4)
    backend = lift.unwrapped.backend
    joint = backend.sim.model.get_joint_qpos_addr(backend.cube.joints[0])
    qpos = backend.sim.data.qpos.copy()
    qpos[joint[0]] += KNOCKED_M + 0.02   # pushed along x across the table
    backend.sim.data.qpos[:] = qpos
    backend.sim.forward()
    *_, info = lift.step(lift.unwrapped.hold_action())
    assert _kind(info) == "knocked_away"


def test_a_gripper_pressed_on_the_table_is_stuck(lift):
    lift.reset(seed=5)
    base = lift.unwrapped
    hold = base.hold_action()
    pos, _ = base.controller_pose()
    backend = base.backend
    cube = backend.sim.data.body_xpos[backend.cube_body_id]
    target = hold.copy()
    # beside the cube (10 cm away along y), below the table top: the fingers press on the table
    target[:3] = [np.ravel(pos)[0], cube[1] + 0.10 if cube[1] < 0.1 else cube[1] - 0.10, 0.78]
    info = {}
    for _ in range(60):
        *_, info = lift.step(target)
    assert _kind(info) == "stuck_against_table"


def test_every_code_has_a_name_and_unknown_codes_are_refused():
    assert [failure_kind_name(i) for i in range(len(FAILURE_KINDS))] == list(FAILURE_KINDS)
    with pytest.raises(ValueError, match="unknown failure kind"):
        failure_kind_name(len(FAILURE_KINDS))
    other = gym.make("JEPA/Square-v0", image_size=32)
    try:
        _, info = other.reset(seed=0)
        assert "failure_kind" not in info, "only the pick tasks name their failures"
    finally:
        other.close()


def test_evaluation_records_carry_the_kind(tmp_path):
    """A policy's rollouts (random weights: it fails) record the kind its episode's last step reported."""
    from jepa_policy.bench import _random_checkpoint
    from jepa_policy.evaluate import evaluate
    from jepa_policy.policy import Policy
    policy = Policy.from_checkpoint(_random_checkpoint("Lift", "cpu", tmp_path / "random.pt"))
    records = evaluate(policy, episodes=2, seed=7, num_envs=2, max_steps=24)["records"]
    assert [r["success"] for r in records] == [False, False]
    assert all(r["failure_kind"] in FAILURE_KINDS[1:] for r in records), records
