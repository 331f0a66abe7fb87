"""The scripted Lift and Can experts and the demonstrations `jepa-envs make-demos Lift|Can` writes: every kept
episode ends in robosuite's own success, seeds give different scenes and motions, the file is the same for one
and two workers, its frames are the live render of its states, and its actions replay its states exactly.

Rendering dominates the cost (tens of ms per frame here), so the experts' episodes are recorded without
cameras and only one Lift demonstration at 16 px is recorded with them.
"""
from __future__ import annotations

import json

import gymnasium as gym
import h5py
import numpy as np
import pytest

pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")

from jepa_envs.cli import ROBOSUITE_EXPERT_TASKS, main  # noqa: E402
from jepa_envs.datasets.hdf5 import load_dataset  # noqa: E402
from jepa_envs.tasks.robosuite_expert import EXPERTS, expert_for, generate_demos  # noqa: E402

pytestmark = pytest.mark.robosuite
SIZE = 16


@pytest.fixture(scope="module")
def lift_raw():
    return generate_demos("Lift", 3, seed=0, images=False)


@pytest.fixture(scope="module")
def can_raw():
    return generate_demos("Can", 2, seed=0, images=False)


@pytest.fixture(scope="module")
def lift_files(tmp_path_factory):
    """The same two Lift demonstrations written by one worker and by two, without camera frames (each frame
    costs tens of ms here; the frames are checked against the states below)."""
    root = tmp_path_factory.mktemp("lift_demos")
    paths = {}
    for workers in (1, 2):
        paths[workers] = root / f"workers{workers}.hdf5"
        assert main(["make-demos", "Lift", "--episodes", "2", "--out", str(paths[workers]), "--seed", "0",
                     "--no-images", "--workers", str(workers)]) == 0
    return paths


@pytest.fixture(scope="module")
def lift_with_images(tmp_path_factory):
    path = tmp_path_factory.mktemp("lift_images") / "demos.hdf5"
    assert main(["make-demos", "Lift", "--episodes", "1", "--out", str(path), "--seed", "0",
                 "--image-size", str(SIZE), "--workers", "1"]) == 0
    return path


def _arrays(path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path, "r") as f:
        f["data"].visititems(lambda name, obj: out.__setitem__(name, obj[()])
                             if isinstance(obj, h5py.Dataset) else None)
        out["env_args"] = json.loads(f["data"].attrs["env_args"])
    return out


@pytest.fixture(scope="module")
def envs():
    """One env per task, cameras off unless a test turns them on, shared by the tests of this module."""
    made = {}

    def get(task: str):
        if task not in made:
            made[task] = gym.make(f"JEPA/{task}-v0", image_size=SIZE).unwrapped
            made[task].reset(seed=0)
        made[task].set_render_images(False)
        return made[task]

    yield get
    for env in made.values():
        env.close()


def _object_position(env, state: np.ndarray) -> np.ndarray:
    env.set_sim_state(state)
    backend = env.backend
    body = backend.cube_body_id if env.task_spec.name == "Lift" else backend.obj_body_id[backend.obj_to_use]
    return np.array(backend.sim.data.body_xpos[body])


def test_the_cli_knows_every_expert():
    assert set(ROBOSUITE_EXPERT_TASKS) == set(EXPERTS)


def test_the_sparse_reward_is_read_from_the_same_state_as_success_on_every_step(envs):
    """robosuite computes its reward before the forward that our step runs; the step that first succeeds could
    return reward 0 with is_success True, so a successful episode's max reward was 0 (12 of Lift JEPA's 188
    successes). Seed 2's expert is such an episode: robosuite's own reward on its success step is 0."""
    task = "Lift"
    env = envs(task)
    expert = expert_for(task, seed=2)
    env.reset(seed=2)
    expert.reset(env)
    rewards, successes = [], []
    for _ in range(env.task_spec.max_episode_steps):
        _, reward, terminated, _, info = env.step(expert.act(env))
        rewards.append(reward)
        successes.append(info["is_success"])
        if terminated:
            break
    assert successes[-1], "the scripted expert should succeed from seed 2"
    assert rewards == [float(s) for s in successes]


@pytest.mark.parametrize("task", ["Lift", "Can"])
def test_each_kept_demo_ends_in_success_and_seeds_differ(task, lift_raw, can_raw, envs):
    episodes, env_args = lift_raw if task == "Lift" else can_raw
    assert env_args["env_name"] == {"Lift": "Lift", "Can": "PickPlaceCan"}[task]
    assert env_args["env_kwargs"]["controller_configs"]["control_delta"] is False
    assert env_args["expert"]["attempts"] == env_args["expert"]["successes"] == len(episodes)
    limit = {"Lift": 150, "Can": 300}[task]
    for ep in episodes:   # success is the env's info["is_success"], robosuite's _check_success(), at the last step
        assert ep["success"] and ep["rewards"][-1] == 1.0 and ep["dones"][-1] == 1
        assert len(ep["actions"]) <= limit and ep["actions"].shape[1] == 10
        assert ep["states"].shape[0] == len(ep["actions"]) and "agentview_image" not in ep["obs"]
    a, b = episodes[:2]
    assert len(a["actions"]) != len(b["actions"]) or not np.allclose(a["actions"], b["actions"])
    first = [_object_position(envs(task), ep["states"][0]) for ep in episodes]
    assert all(np.linalg.norm(p - q) > 1e-3 for i, p in enumerate(first) for q in first[i + 1:])


def test_one_and_two_workers_write_the_same_file(lift_files):
    one, two = (_arrays(p) for p in (lift_files[1], lift_files[2]))
    assert sorted(one) == sorted(two) and "demo_1/states" in one and "demo_0/obs/agentview_image" not in one
    for key in one:
        if key == "env_args":
            assert one[key] == two[key] and one[key]["expert"]["images"] is False
        else:
            np.testing.assert_array_equal(one[key], two[key], err_msg=key)


def test_the_file_with_frames_loads_and_holds_the_same_episode(lift_with_images, lift_raw):
    """The expert reads the simulator, so recording the cameras changes nothing but the frames."""
    stored = _arrays(lift_with_images)
    assert stored["demo_0/obs/agentview_image"].shape[1:] == (SIZE, SIZE, 3)
    assert stored["env_args"]["env_kwargs"]["camera_heights"] == SIZE
    np.testing.assert_array_equal(stored["demo_0/actions"], lift_raw[0][0]["actions"])
    np.testing.assert_array_equal(stored["demo_0/states"], lift_raw[0][0]["states"])
    demos = load_dataset(lift_with_images, cache_dir=False)
    assert demos.num_episodes() == 1 and demos.spec.name == "Lift" and demos.actions.shape[1] == 10


def test_stored_frames_are_the_live_render_of_the_stored_states(lift_with_images, envs):
    """Every 8th stored frame and the last, both cameras and the low-dim keys, against a render of the stored
    state in an env that did not record them."""
    stored = _arrays(lift_with_images)
    env = envs("Lift")
    env.set_render_images(True)
    states = stored["demo_0/states"]
    for t in sorted({*range(0, len(states), 8), len(states) - 1}):
        env.set_sim_state(states[t])
        live = env.observe_now()
        assert sorted(live) == sorted(k.split("/")[-1] for k in stored if k.startswith("demo_0/obs/"))
        for key, value in live.items():
            np.testing.assert_array_equal(stored[f"demo_0/obs/{key}"][t], value, err_msg=f"step {t} {key}")


@pytest.mark.parametrize("task", ["Lift", "Can"])
def test_actions_replayed_open_loop_reproduce_the_states_exactly(task, lift_raw, can_raw, envs):
    """Replaying the stored actions from each stored first state passes through every stored state, bit for bit
    (the simulation is deterministic and a seeded reset leaves nothing of the previous episode), and ends in
    robosuite's own success."""
    env = envs(task)
    for ep in (lift_raw if task == "Lift" else can_raw)[0]:
        env.reset(seed=ep["seed"], options={"state": ep["states"][0]})
        assert not env.backend._check_success()
        for t, action in enumerate(ep["actions"]):
            np.testing.assert_array_equal(env.backend.sim.get_state().flatten(), ep["states"][t], err_msg=str(t))
            env.step(action)
        assert env.backend._check_success()


def test_a_missed_grasp_is_retried(envs):
    """The cube taken from between the open fingers just before they close: the expert finds its gripper empty,
    opens, rises, approaches the cube where it now is and still lifts it."""
    env = envs("Lift")
    expert = expert_for("Lift", seed=1)
    env.reset(seed=1)
    expert.reset(env)
    joint, moved, held = env.backend.cube.joints[0], False, 0
    for _ in range(env.task_spec.max_episode_steps):
        if expert.phase == "close" and not moved:
            qpos = env.backend.sim.data.get_joint_qpos(joint).copy()
            qpos[0] += 0.08
            env.backend.sim.data.set_joint_qpos(joint, qpos)
            env.backend.sim.forward()
            moved = True
        *_, info = env.step(expert.act(env))
        held = held + 1 if info["is_success"] else 0
        if held >= expert.finish_steps:
            break
    assert moved and expert.retries == 1 and env.backend._check_success()


def test_make_demos_refuses_options_of_other_experts(tmp_path):
    out = str(tmp_path / "x.hdf5")
    with pytest.raises(SystemExit, match="--difficulty and --finish-threshold are PushT's options"):
        main(["make-demos", "Lift", "--episodes", "1", "--out", out, "--finish-threshold", "0.9"])
    with pytest.raises(SystemExit, match="--no-images is for the robosuite tasks"):
        main(["make-demos", "PushT", "--episodes", "1", "--out", out, "--no-images"])
    with pytest.raises(SystemExit, match="no scripted expert exists for Square .*experts for PushT, PushTStandard, "
                                         "Lift, Can"):
        main(["make-demos", "Square", "--episodes", "1", "--out", out])


def test_without_reflections_the_file_says_so_and_every_reader_draws_it_so(tmp_path):
    """make-demos --no-reflections records the setting; a file written without frames and rendered afterwards
    holds the very frames a file recorded with frames holds (same seeds, same states, same cube: render-dataset
    once rebuilt the model at each reset and redrew the cube's size from the reset seed, up to 2 mm off the
    recorded one) and keeps the source's setting; the env rebuilt from the file's env_args (as evaluation builds
    it) renders those frames too, and they differ from the frames with the table's reflection."""
    path = tmp_path / "plain.hdf5"
    assert main(["make-demos", "Lift", "--episodes", "1", "--out", str(path), "--seed", "0", "--no-reflections",
                 "--image-size", str(SIZE), "--workers", "1", "--no-progress"]) == 0
    plain = _arrays(path)
    assert plain["env_args"]["render"] == {"reflections": False}
    raw = tmp_path / "raw.hdf5"
    assert main(["make-demos", "Lift", "--episodes", "1", "--out", str(raw), "--seed", "0", "--no-images",
                 "--no-reflections", "--image-size", str(SIZE), "--workers", "1", "--no-progress"]) == 0
    rendered = tmp_path / "rendered.hdf5"
    assert main(["render-dataset", str(raw), str(rendered), "--size", str(SIZE), "--no-progress"]) == 0
    again = _arrays(rendered)
    assert again["env_args"]["render"] == {"reflections": False}
    for key in ("demo_0/obs/agentview_image", "demo_0/obs/robot0_eye_in_hand_image"):
        assert np.array_equal(plain[key], again[key]), key
    key = "demo_0/obs/agentview_image"
    env = gym.make("JEPA/Lift-v0", image_size=SIZE, env_args=plain["env_args"]).unwrapped
    try:
        env.reset(seed=0, options={"state": plain["demo_0/states"][0]})
        for t in (0, len(plain["demo_0/states"]) - 1):
            env.set_sim_state(plain["demo_0/states"][t])
            assert np.array_equal(env.observe_now()["agentview_image"], plain[key][t]), t
        env.reflections = True   # the same state with the table's reflection: another frame
        assert not np.array_equal(env.observe_now()["agentview_image"], plain[key][-1])
    finally:
        env.close()
    with pytest.raises(SystemExit, match="--no-reflections is for the robosuite tasks"):
        main(["make-demos", "PushT", "--episodes", "1", "--out", str(tmp_path / "p.hdf5"), "--no-reflections"])
