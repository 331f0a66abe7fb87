"""robomimic tasks on robosuite: gymnasium compliance, spaces, seeding, absolute actions, env_args, conversion.

Envs are expensive to build (seconds) and to render (tens of ms per camera frame), so each is built once
per module at a small image size, and most steps run with camera rendering switched off.
"""
import json

import gymnasium as gym
import h5py
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")

import jepa_envs  # noqa: E402,F401  registers the ids
from jepa_envs.tasks import abs_actions, rotations  # noqa: E402
from jepa_envs.datasets import convert_abs_actions
from jepa_envs.tasks.robomimic_env import (  # noqa: E402
    RobomimicEnv, env_args_from_hdf5, make_backend_from_env_args, robomimic_env_args)

SIZE = 32


@pytest.fixture(scope="module")
def square():
    env = gym.make("JEPA/Square-v0", image_size=SIZE)
    yield env.unwrapped
    env.close()


@pytest.fixture(scope="module")
def square_args_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("robomimic") / "square_env_args.hdf5"
    with h5py.File(path, "w") as f:
        f.create_group("data").attrs["env_args"] = json.dumps(
            robomimic_env_args("NutAssemblySquare", ("agentview", "robot0_eye_in_hand"), 84))
    return path


@pytest.fixture(scope="module")
def square_delta(square_args_file):
    env = RobomimicEnv.from_hdf5(square_args_file, image_size=SIZE, action_mode="delta")
    yield env
    env.close()


@pytest.fixture(scope="module")
def transport():
    env = RobomimicEnv("Transport", image_size=SIZE)
    yield env
    env.close()


def _target_pose(env, offset, angle):
    pos, mats = env.controller_pose()
    target_m = mats @ rotations.axis_angle_to_matrix(np.array([0.0, 0.0, angle]))
    return pos + np.asarray(offset), target_m


def test_square_passes_gymnasium_check_env(square):
    check_env(square, skip_render_check=True)


def test_toolhang_passes_check_env_without_disturbing_other_envs_images(square):
    """Several envs share one process (vector envs): building, stepping and closing one must not change the
    images of another (robosuite renders into whatever GL context is current)."""
    before, _ = square.reset(seed=11)
    env = RobomimicEnv("ToolHang", image_size=SIZE)
    try:
        check_env(env, skip_render_check=True)
        assert env.task_spec.image_keys == ("sideview_image", "robot0_eye_in_hand_image")
    finally:
        env.close()
    after, _ = square.reset(seed=11)
    for key in square.task_spec.image_keys:
        np.testing.assert_array_equal(after[key], before[key])


def test_transport_passes_check_env(transport):
    check_env(transport, skip_render_check=True)


def test_spaces_follow_the_task_spec(square, transport):
    for env, arms in ((square, 1), (transport, 2)):
        spec = env.task_spec
        assert spec.image_size == SIZE
        assert set(env.observation_space.spaces) == set(spec.image_keys) | set(spec.lowdim_keys)
        assert env.action_space.shape == (10 * arms,) == (spec.action_dim,)
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        for key in spec.image_keys:
            assert obs[key].shape == (SIZE, SIZE, 3) and obs[key].dtype == np.uint8 and obs[key].max() > 0
        for key, dim in spec.lowdim:
            assert obs[key].shape == (dim,) and obs[key].dtype == np.float32
        assert type(info["is_success"]) is bool
    assert transport.task_spec.image_keys == ("shouldercamera0_image", "shouldercamera1_image",
                                             "robot0_eye_in_hand_image", "robot1_eye_in_hand_image")


def test_robomimic_settings(square, transport):
    for env in (square, transport):
        b = env.backend
        assert b.control_freq == 20 and b.reward_shaping is False and b.ignore_done is True
        for robot in b.robots:
            assert robot.controller.name == "OSC_POSE" and robot.controller_config["type"] == "OSC_POSE"
            np.testing.assert_allclose(robot.controller.kp, 150)
            assert robot.controller.use_delta is False  # abs mode
    assert transport.backend.env_configuration == "single-arm-opposed"


def test_seeded_resets_are_reproducible_and_seeds_differ(square):
    a, _ = square.reset(seed=7)
    nut_a = square.backend.sim.data.qpos.copy()
    b, _ = square.reset(seed=7)
    np.testing.assert_array_equal(square.backend.sim.data.qpos, nut_a)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    square.reset(seed=8)
    assert not np.allclose(square.backend.sim.data.qpos, nut_a)


def test_step_reports_success_flag_and_images_right_way_up(square):
    obs, _ = square.reset(seed=0)
    obs, reward, terminated, truncated, info = square.step(square.hold_action())
    assert type(info["is_success"]) is bool and info["is_success"] is False
    assert terminated is False and truncated is False and isinstance(reward, float)
    # agentview looks down at the table: the robot's dark base is at the top, the bright table fills the bottom
    img = obs["agentview_image"].astype(float).mean(axis=2)
    assert img[SIZE // 2:].mean() > img[: SIZE // 4].mean()


def test_render_off_really_skips_camera_rendering(square):
    square.reset(seed=0)
    sim = square.backend.sim
    calls = []
    original = sim.render

    def counting_render(*args, **kwargs):
        calls.append(kwargs.get("camera_name"))
        return original(*args, **kwargs)

    sim.render = counting_render
    try:
        square.set_render_images(False)
        obs, *_ = square.step(square.hold_action())
        assert calls == []
        assert all(obs[k].shape == (SIZE, SIZE, 3) and not obs[k].any() for k in square.task_spec.image_keys)
        square.set_render_images(True)
        obs, *_ = square.step(square.hold_action())
        assert sorted(calls) == sorted(square.task_spec.cameras)
        on_demand = obs
        # the frame rendered on demand equals the one an always-rendering env shows at that step
        square.reset(seed=0)
        square.step(square.hold_action())
        always, *_ = square.step(square.hold_action())
        for key in square.task_spec.image_keys:
            assert on_demand[key].any()
            np.testing.assert_array_equal(on_demand[key], always[key])
        # images switched on right after a reset made without them are real frames, not placeholders
        square.set_render_images(False)
        square.reset(seed=0)
        square.set_render_images(True)
        obs, *_ = square.step(square.hold_action())
        assert all(obs[key].any() for key in square.task_spec.image_keys)
    finally:
        sim.render = original
        square.set_render_images(True)


@pytest.mark.parametrize("env_name", ["square", "transport"])
def test_absolute_action_sets_controller_goal_exactly_and_reaches_it(env_name, request):
    env = request.getfixturevalue(env_name)
    env.reset(seed=1)
    env.set_render_images(False)
    try:
        target_p, target_m = _target_pose(env, [0.04, -0.03, 0.05], 0.35)
        action = abs_actions.pose_to_abs(target_p, target_m, np.full(env.num_arms, -1.0))
        native = env.to_native(action)
        assert native.shape == (7 * env.num_arms,)
        np.testing.assert_allclose(abs_actions.native_to_abs(native, env.num_arms), action, atol=1e-12)
        env.step(action)
        goal_p, goal_m = env.controller_goal()
        np.testing.assert_allclose(goal_p, target_p, atol=1e-9)
        # robosuite turns the axis-angle into a matrix in float32
        np.testing.assert_allclose(goal_m, target_m, atol=1e-6)
        for _ in range(40):
            env.step(action)
        pos, mats = env.controller_pose()
        assert np.all(np.linalg.norm(pos - target_p, axis=1) < 0.005)
        assert np.all(rotations.rotation_angle_between(mats, target_m) < 0.02)
    finally:
        env.set_render_images(True)


def test_delta_mode_and_env_args_file(square_delta, square_args_file):
    env = square_delta
    assert env.action_space.shape == (7,)
    assert env.env_args == env_args_from_hdf5(square_args_file)
    assert env.backend.robots[0].controller.use_delta is True
    np.testing.assert_array_equal(env.native_zero_action(), np.zeros(7))
    with pytest.raises(ValueError, match=r"shape \(7,\)"):
        env.step(np.zeros(10))


def test_bad_env_args_are_refused_with_a_reason(square_args_file):
    args = env_args_from_hdf5(square_args_file)
    with pytest.raises(ValueError, match="ToolHang"):
        RobomimicEnv("ToolHang", env_args=args)
    new_format = json.loads(json.dumps(args))
    new_format["env_kwargs"]["controller_configs"] = {"type": "BASIC", "body_parts": {}}
    with pytest.raises(ValueError, match="robosuite 1.4.1"):
        RobomimicEnv.from_env_args(new_format)
    with pytest.raises(ValueError, match="action_mode"):
        RobomimicEnv("Square", action_mode="joint")
    with pytest.raises(KeyError, match="env_args"):
        env_args_from_hdf5(_empty_h5(square_args_file.parent / "empty.hdf5"))
    with pytest.raises(KeyError, match="NoSuchEnv"):
        RobomimicEnv.from_env_args({**args, "env_name": "NoSuchEnv"})
    with pytest.raises(ValueError, match="robosuite has no env 'NoSuchEnv'"):
        make_backend_from_env_args({**args, "env_name": "NoSuchEnv"}, control_delta=True)


def test_env_args_from_robomimics_convert_robosuite_build_the_env():
    """robomimic's convert_robosuite.py (v0.3.0) turns robosuite's demonstration file into env_args by copying its
    env_info, which names env_name, into env_kwargs as it is; building from them raised 'make() got multiple values
    for argument env_name' (found by `make interop`: render-dataset on robomimic's converted Lift demos)."""
    import robosuite

    src = f"{robosuite.__path__[0]}/models/assets/demonstrations/lift/demo.hdf5"
    with h5py.File(src) as f:   # convert_robosuite.py's env_meta, line for line
        env_args = {"type": 1, "env_name": f["data"].attrs["env"],
                    "env_version": f["data"].attrs["repository_version"],
                    "env_kwargs": json.loads(f["data"].attrs["env_info"])}
    assert env_args["env_kwargs"]["env_name"] == "Lift"
    backend = make_backend_from_env_args(env_args, control_delta=True, use_camera_obs=False)
    try:
        assert type(backend).__name__ == "Lift" and backend.robots[0].controller.use_delta
    finally:
        backend.close()


def _empty_h5(path):
    with h5py.File(path, "w") as f:
        f.create_group("data")
    return path


def test_convert_abs_actions_replays_the_delta_trajectory(square_delta, square, square_args_file, tmp_path):
    """Record a delta rollout, convert it, replay the absolute actions: the arm follows the same path."""
    env = square_delta
    env.reset(seed=3)
    env.set_render_images(False)
    rng = np.random.default_rng(0)
    states, deltas, eef = [], [], []
    for t in range(30):
        delta = np.concatenate([0.6 * np.sin(t / 6 + np.arange(3)), 0.4 * np.cos(t / 5 + np.arange(3)),
                                [1.0 if t > 15 else -1.0]]) + 0.05 * rng.normal(size=7)
        states.append(env.backend.sim.get_state().flatten())
        deltas.append(np.clip(delta, -1, 1))
        obs, *_ = env.step(deltas[-1])
        eef.append(obs["robot0_eef_pos"])
    env.set_render_images(True)
    src = tmp_path / "delta.hdf5"
    with h5py.File(square_args_file, "r") as f_args, h5py.File(src, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = f_args["data"].attrs["env_args"]
        demo = data.create_group("demo_0")
        demo["states"], demo["actions"] = np.array(states), np.array(deltas, dtype=np.float32)
    out = convert_abs_actions.convert_abs_actions(src, tmp_path / "abs.hdf5", progress=False)
    with h5py.File(out, "r") as f:
        abs_act = f["data/demo_0/actions"][()]
        np.testing.assert_array_equal(f["data/demo_0/actions_delta"][()], np.array(deltas, dtype=np.float32))
        assert json.loads(f["data"].attrs["env_args"])["env_kwargs"]["controller_configs"]["control_delta"] is False
        assert f["data"].attrs["action_convention"] == "abs_pos_rot6d_gripper"
    assert abs_act.shape == (30, 10)
    np.testing.assert_allclose(np.linalg.norm(abs_act[:, 3:6], axis=1), 1.0, atol=1e-6)

    square.reset(seed=3)
    square.set_render_images(False)
    try:
        square.backend.sim.set_state_from_flattened(states[0])
        square.backend.sim.forward()
        replay = [square.step(a)[0]["robot0_eef_pos"] for a in abs_act]
    finally:
        square.set_render_images(True)
    err = np.linalg.norm(np.array(replay) - np.array(eef), axis=1)
    assert err.max() < 1e-5, err  # measured ~1e-8 m: the absolute goals reproduce the delta rollout
    with pytest.raises(ValueError, match="different env"):
        convert_abs_actions.delta_to_abs_by_replay(env.backend, np.zeros((2, 5)), np.zeros((2, 7)))
    with pytest.raises(ValueError, match="last dimension 7"):
        convert_abs_actions.delta_to_abs_by_replay(env.backend, np.array(states[:2]), np.zeros((2, 10)))
    with pytest.raises(ValueError, match="already holds absolute"):
        convert_abs_actions.convert_abs_actions(out, tmp_path / "again.hdf5", progress=False)


def test_reading_the_hold_pose_changes_nothing(square):
    """``controller_pose`` (the bridge's jump-limit reference, ``hold_action``) reads a copy of the state: the
    same seeded actions reach bit-identical states whether or not it is read between steps, and it equals the
    pose the controller itself computes."""
    def rollout(read_pose: bool, actions=None):
        square.set_render_images(False)
        square.reset(seed=0)
        actions = actions if actions is not None else [square.hold_action()] * 20
        states = []
        for action in actions:
            if read_pose:
                square.hold_action()
            square.step(action)
            states.append(square.backend.sim.data.qpos.copy())
        square.set_render_images(True)
        return np.array(states), actions

    plain, actions = rollout(False)
    probed, _ = rollout(True, actions)
    assert np.array_equal(plain, probed)
    pos, mats = square.controller_pose()
    controller = square.backend.robots[0].controller
    controller.update(force=True)
    assert np.allclose(pos[0], controller.ee_pos, atol=1e-12) and np.allclose(mats[0], controller.ee_ori_mat)


_FINGERPRINT = """
import hashlib, sys
import numpy as np
np.random.seed(int(sys.argv[1]))   # each process's global RNG elsewhere, as two independent runs have it
import gymnasium as gym
import jepa_envs
env = gym.make("JEPA/Transport-v0", image_size=16).unwrapped
model = env.backend.sim.model
obs, _ = env.reset(seed=7)
for _ in range(3):
    obs, *_ = env.step(env.hold_action())
digest = lambda *arrays: hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()[:12]
print(digest(model.geom_size, model.geom_pos, model.body_mass, model.geom_friction), hashlib.sha1(
    model.get_xml().encode()).hexdigest()[:12], digest(*[obs[k] for k in sorted(obs)]))
"""


@pytest.mark.slow
def test_transport_is_the_same_scene_in_two_processes():
    """robosuite builds Transport's hammer (radius, length, density, friction) from numpy's global RNG while the
    env is made, before any seeded reset: two processes with the same reset seed saw different geometry, masses,
    images and trajectories. Construction is seeded now."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "osmesa")}
    runs = [subprocess.Popen([sys.executable, "-c", _FINGERPRINT, str(seed)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=env) for seed in (1, 2)]
    outs = []
    for run in runs:
        out, err = run.communicate(timeout=300)
        assert run.returncode == 0, err[-2000:]
        outs.append(out.strip().splitlines()[-1])
    geometry, xml, observation = (list(part) for part in zip(*(o.split() for o in outs)))
    assert geometry[0] == geometry[1] and xml[0] == xml[1], outs
    assert observation[0] == observation[1], outs


@pytest.mark.parametrize("task", ["Square", "ToolHang"])
def test_every_action_in_the_space_steps_and_a_degenerate_rotation_holds_the_orientation(task, square):
    """action_space.contains(zeros) is true, so step(zeros) must work (it raised on the 6-D rotation's zero
    column): an arm whose rotation is degenerate holds its current orientation; sampled actions step too."""
    env = square if task == "Square" else RobomimicEnv(task, image_size=SIZE)
    env.reset(seed=2)
    env.set_render_images(False)
    try:
        env.action_space.seed(0)
        for _ in range(3):
            env.step(env.action_space.sample())
        zeros = np.zeros(env.action_space.shape, np.float32)
        assert env.action_space.contains(zeros)
        _, before = env.controller_pose()
        env.step(zeros)
        goal_p, goal_m = env.controller_goal()
        np.testing.assert_allclose(goal_m, before, atol=1e-6)   # robosuite keeps the goal in float32
        np.testing.assert_allclose(goal_p, np.zeros((1, 3)), atol=1e-9)   # the position is taken as given
    finally:
        env.set_render_images(True)
        if env is not square:
            env.close()


def test_a_degenerate_rotation_holds_only_its_own_arm(transport):
    transport.reset(seed=3)
    transport.set_render_images(False)
    try:
        action = transport.hold_action()
        target_p, target_m = _target_pose(transport, [0.0, 0.0, 0.0], 0.3)
        action[13:19] = rotations.matrix_to_rot6d(target_m[1])   # arm 1 turns
        action[3:9] = [1, 0, 0, 2, 0, 0]                          # arm 0: parallel columns
        _, before = transport.controller_pose()
        transport.step(action)
        _, goal_m = transport.controller_goal()
        np.testing.assert_allclose(goal_m[0], before[0], atol=1e-6)
        np.testing.assert_allclose(goal_m[1], target_m[1], atol=1e-6)
    finally:
        transport.set_render_images(True)


def test_bench_raw_arm_renders_what_ours_renders(square):
    """`jepa-envs bench`'s overhead column compares like with like: the raw robosuite step renders the same
    camera frames as our step (it rendered none since our cameras stopped sampling on robosuite's clock, and
    Square's "overhead" read +1112 %)."""
    from jepa_envs.bench import _hold_step, _raw_step

    square.reset(seed=0)
    sim = square.backend.sim
    calls = []
    original = sim.render

    def counting_render(*args, **kwargs):
        calls.append(kwargs.get("camera_name"))
        return original(*args, **kwargs)

    sim.render = counting_render
    try:
        _raw_step(square)()
        raw, calls[:] = list(calls), []
        _hold_step(square)()
        assert sorted(raw) == sorted(calls) == sorted(square.task_spec.cameras)
    finally:
        sim.render = original
