"""The standard PushT (gym-pusht 0.1.8's task behind our interface): its facts, its reset per seed, its frames and
states against gym-pusht's own recorded outputs, its observation types, info keys and refusals."""
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pymunk
import pytest
from gymnasium.utils import seeding
from gymnasium.utils.env_checker import check_env
from PIL import Image

import jepa_envs  # noqa: F401
from jepa_envs.tasks import pusht_standard as std
from jepa_envs.tasks.pusht import PushTEnv
from jepa_envs.tasks.pusht_expert import generate_demos
from jepa_envs.tasks.pusht_standard import PushTStandardEnv

# gym-pusht 0.1.8's own outputs (2 seeds x 30 steps of random and of expert actions), written by
# `python scripts/interop_pusht.py --fixture ...` from gym-pusht running in its own venv (pymunk 6)
REFERENCE = Path(__file__).parent / "data" / "gym_pusht_0.1.8_reference.npz"


@pytest.fixture(scope="module")
def reference():
    with np.load(REFERENCE) as data:
        return {k: data[k] for k in data.files}


def _make(**kwargs):
    return gym.make("JEPA/PushTStandard-v0", **kwargs)


@pytest.mark.parametrize("actions", ["random", "expert"])
def test_states_and_frames_equal_gym_pushts_recorded_ones(reference, actions):
    env = _make(obs_type="pixels_agent_pos")
    try:
        for i, seed in enumerate(reference[f"{actions}_seeds"]):
            obs, info = env.reset(seed=int(seed))
            for t in range(reference[f"{actions}_actions"].shape[1] + 1):
                if t:
                    obs, reward, terminated, _, info = env.step(reference[f"{actions}_actions"][i, t - 1])
                    assert reward == pytest.approx(reference[f"{actions}_reward"][i, t], abs=1e-12)
                    assert terminated == reference[f"{actions}_terminated"][i, t]
                state = [*info["pos_agent"], *info["block_pose"]]
                np.testing.assert_array_equal(state, reference[f"{actions}_state"][i, t])
                np.testing.assert_array_equal(obs["pixels"], reference[f"{actions}_pixels"][i, t])
                np.testing.assert_array_equal(obs["agent_pos"], reference[f"{actions}_agent_pos"][i, t])
                assert info["n_contacts"] == reference[f"{actions}_n_contacts"][i, t]
                assert info["coverage"] == pytest.approx(reference[f"{actions}_coverage"][i, t], abs=1e-12)
                np.testing.assert_array_equal(env.unwrapped.keypoints().reshape(-1),
                                              reference[f"{actions}_keypoints"][i, t])
    finally:
        env.close()
    assert reference["random_n_contacts"].any(), "the recorded frames include contact marks"


def test_the_scene_is_built_as_gym_pusht_builds_it():
    sim = std.StandardPushTSim()
    try:
        block = sim.block
        assert (block.mass, block.moment) == (1.0, 3000.0)   # the bar's moment about its edge, counted twice
        assert tuple(block.center_of_gravity) == (0.0, 45.0)
        assert sorted(map(tuple, (v for part in sim.local_vertices for v in part))) == sorted(std.BAR + std.STEM)
        shapes = list(sim.space.shapes)
        assert all(s.friction == 0.0 and s.elasticity == 0.0 for s in shapes)
        walls = [s for s in shapes if isinstance(s, pymunk.Segment)]
        assert sorted((tuple(s.a), tuple(s.b), s.radius) for s in walls) == sorted(
            (tuple(map(float, a)), tuple(map(float, b)), 2.0) for a, b in std.WALLS)
        agent = next(s for s in shapes if isinstance(s, pymunk.Circle))
        assert agent.radius == 15.0 and agent.body.body_type == pymunk.Body.KINEMATIC
        assert sim.space.damping == 0.0 and tuple(sim.space.gravity) == (0.0, 0.0)
    finally:
        sim.free()


def test_reset_draws_gym_pushts_state_from_the_seed_and_sets_it_the_legacy_way():
    env = _make(obs_type="state")
    try:
        for seed in (0, 7, 123):
            obs, info = env.reset(seed=seed)
            rng, _ = seeding.np_random(seed)
            ax, ay = rng.integers(50, 450), rng.integers(50, 450)
            bx, by = rng.integers(100, 400), rng.integers(100, 400)
            angle = rng.uniform(-np.pi, np.pi)
            assert tuple(info["pos_agent"]) == (ax, ay)
            # position set at angle 0, then the angle turns the block about its centre of gravity (0, 45)
            cog = np.array([bx, by + 45.0])
            origin = cog - 45.0 * np.array([-math.sin(angle), math.cos(angle)])
            np.testing.assert_allclose(info["block_pose"], [*origin, angle], atol=1e-9)
            assert obs[4] == pytest.approx(angle % (2 * np.pi))
            assert info["is_success"] is False and set(info) >= {"pos_agent", "vel_agent", "block_pose", "goal_pose",
                                                                  "n_contacts", "is_success"}
    finally:
        env.close()


def test_reset_to_state_reproduces_gym_pushts_documented_example():
    # gym-pusht's docstring: reset_to_state [0, 10, 20, 30, 1] gives the state [0, 10, 57.866196, 50.686398, 1]
    env = _make(obs_type="state")
    try:
        state, _ = env.reset(options={"reset_to_state": [0.0, 10.0, 20.0, 30.0, 1.0]})
        np.testing.assert_allclose(state.astype(np.float32), [0.0, 10.0, 57.866196, 50.686398, 1.0], atol=1e-5)
        exact, _ = env.reset(options={"state": [1.0, 2.0, 300.0, 200.0, 0.5]})   # ours: exactly this state
        np.testing.assert_allclose(exact, [1.0, 2.0, 300.0, 200.0, 0.5], atol=1e-9)
        with pytest.raises(ValueError, match="reset_to_state.*or 'state'"):
            env.reset(options={"reset_state": [0, 0, 0, 0, 0]})
        with pytest.raises(ValueError, match="5 finite numbers"):
            env.reset(options={"reset_to_state": [0, 0, 0]})
    finally:
        env.close()


def test_reward_success_and_termination_follow_coverage_over_095():
    env = _make()
    try:
        env.reset(options={"state": [60.0, 60.0, *std.GOAL_POSE]})
        _, reward, terminated, truncated, info = env.step([60.0, 60.0])
        assert info["coverage"] == pytest.approx(1.0) and reward == 1.0 and terminated and info["is_success"]
        assert not truncated
        env.reset(options={"state": [60.0, 60.0, std.GOAL_POSE[0], std.GOAL_POSE[1] + 20, std.GOAL_POSE[2]]})
        _, reward, terminated, _, info = env.step([60.0, 60.0])
        assert 0 < info["coverage"] < 0.95 and reward == pytest.approx(info["coverage"] / 0.95)
        assert not terminated and not info["is_success"]
        assert std.coverage((500.0, 500.0, 0.0)) == 0.0
    finally:
        env.close()
    assert gym.spec("JEPA/PushTStandard-v0").max_episode_steps == 300


@pytest.mark.parametrize("obs_type", std.OBS_TYPES)
def test_every_obs_type_passes_check_env(obs_type):
    env = PushTStandardEnv(obs_type=obs_type)
    try:
        check_env(env, skip_render_check=True)
        obs, _ = env.reset(seed=3)
        assert env.observation_space.contains(obs)
    finally:
        env.close()


def test_keypoints_are_the_ts_corners():
    env = _make(obs_type="environment_state_agent_pos")
    try:
        obs, info = env.reset(seed=4)
        corners = np.array([c for part in std.t_parts(info["block_pose"]) for c in part])
        np.testing.assert_allclose(np.sort(obs["environment_state"].reshape(8, 2), 0), np.sort(corners, 0), atol=1e-9)
    finally:
        env.close()


def test_frame_content_goal_block_agent_walls_in_their_colours():
    env = _make(obs_type="pixels", observation_width=512, observation_height=512)   # no resize: the scene itself
    try:
        frame, info = env.reset(options={"state": [100.0, 400.0, 380.0, 120.0, 0.0]})
        assert tuple(frame[256, 256]) == std.COLORS["goal"]            # the goal T's body origin is on the T
        assert tuple(frame[135, 380]) == std.COLORS["block_fill"]      # inside the bar (y 120..150)
        assert tuple(frame[121, 380]) == std.COLORS["block_edge"]      # its top edge, 4 px thick
        assert tuple(frame[400, 100]) == std.COLORS["agent_inner"]
        assert tuple(frame[400, 100 + 13]) == std.COLORS["agent"]      # between radius 11 and 15
        assert tuple(frame[300, 5]) == std.COLORS["wall"] and tuple(frame[300, 40]) == std.COLORS["background"]
    finally:
        env.close()


def test_the_walls_lie_where_the_frame_redraws_them():
    rows, cols = std._WALL_PIXELS
    assert ((rows < 12) | (rows >= 500) | (cols < 12) | (cols >= 500)).all()


def test_top_image_is_the_frame_resized_as_the_data_loader_resizes():
    env = _make(image_size=48)
    try:
        obs, _ = env.reset(seed=2)
        frame = env.unwrapped.backend.render(96, 96)
        expected = np.asarray(Image.fromarray(frame).resize((48, 48), Image.BILINEAR))
        np.testing.assert_array_equal(obs["top_image"], expected)
        assert obs["agent_pos"].dtype == np.float32 and env.unwrapped.task_spec.image_size == 48
        env.unwrapped.set_render_images(False)
        assert not env.step(env.unwrapped.hold_action())[0]["top_image"].any()
    finally:
        env.close()


def test_render_gives_the_visualisation_frame_with_the_action_marked():
    env = _make(render_mode="rgb_array", visualization_width=340, visualization_height=340)
    try:
        env.reset(seed=0)
        env.step([128.0, 384.0])
        frame = env.render()
        assert frame.shape == (340, 340, 3)
        assert tuple(frame[int(384 / 512 * 340), int(128 / 512 * 340)]) == std.COLORS["marker"]
    finally:
        env.close()
    env = _make()
    try:
        env.reset(seed=0)
        assert env.render() is None
    finally:
        env.close()


def test_render_takes_any_visualisation_size_and_marks_the_action_where_gym_pusht_does():
    """gym-pusht scales the marker's x by the frame's height and its y by its width (``action / 512 * [height,
    width]``); on a non-square frame ours puts it at the same pixel (make interop compares the frames)."""
    env = _make(render_mode="rgb_array", visualization_width=384, visualization_height=256)
    try:
        env.reset(seed=0)
        env.step([256.0, 128.0])
        frame = env.render()
        assert frame.shape == (256, 384, 3)
        assert tuple(frame[int(128 / 512 * 384), int(256 / 512 * 256)]) == std.COLORS["marker"]
    finally:
        env.close()


def test_variants_are_one_keyword_apart_and_unknown_ones_are_named():
    standard = gym.make("JEPA/PushT-v0", variant="standard")
    embedded = gym.make("JEPA/PushT-v0")
    try:
        assert isinstance(standard.unwrapped, PushTStandardEnv) and isinstance(embedded.unwrapped, PushTEnv)
        assert standard.unwrapped.task_spec.name == "PushTStandard" and embedded.unwrapped.task_spec.name == "PushT"
    finally:
        standard.close()
        embedded.close()
    with pytest.raises(ValueError, match="unknown PushT variant 'gym'; known variants: embedded .* standard"):
        gym.make("JEPA/PushT-v0", variant="gym")
    with pytest.raises(ValueError, match="is the standard PushT; variant='embedded'"):
        gym.make("JEPA/PushTStandard-v0", variant="embedded")


@pytest.mark.parametrize("kwargs, message", [
    ({"difficulty": "easy"}, "unknown option.*difficulty presets belong to the embedded PushT"),
    ({"obs_type": "rgb"}, "unknown obs_type 'rgb'"),
    ({"render_mode": "human"}, "render_mode='human' is not supported"),
    ({"observation_width": 96, "observation_height": 64}, "must be equal"),
    ({"obs_type": "pixels", "image_size": 48}, "image_size sets obs_type='jepa'"),
    ({"visualization_width": 0}, "visualization_width must be >= 8"),
    ({"observation_width": 0, "observation_height": 0}, "observation_width must be >= 8 pixels, got 0"),  # was 96
    ({"obs_type": "pixels", "observation_width": 0}, "observation_width must be >= 8 pixels, got 0"),
])
def test_bad_options_are_refused_naming_the_problem(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=message):
        _make(**kwargs)


def test_a_closed_env_says_so_at_step_reset_and_render():
    """step after close raised AttributeError from deep inside the simulator."""
    env = _make(render_mode="rgb_array")
    env.reset(seed=0)
    env.close()
    for call in (lambda: env.step([256.0, 256.0]), lambda: env.reset(seed=1), env.render):
        with pytest.raises(RuntimeError, match="PushTStandardEnv was closed; make a new env"):
            call()


def test_bad_actions_are_refused():
    env = _make()
    try:
        env.reset(seed=0)
        for bad in ([1.0], [np.nan, 3.0]):
            with pytest.raises(ValueError, match="2 finite numbers"):
                env.step(bad)
    finally:
        env.close()


def test_the_expert_pushes_the_standard_t_to_success_and_records_the_task():
    episodes, env_args = generate_demos(1, seed=5, task="PushTStandard")
    assert episodes[0]["success"] and len(episodes[0]["actions"]) < 300
    assert episodes[0]["obs"]["top_image"].shape[1:] == (96, 96, 3)
    assert env_args["env_name"] == "PushTStandard" and env_args["env_kwargs"] == {"image_size": 96}
    assert env_args["expert"]["finish_threshold"] == 0.95
    with pytest.raises(TypeError, match="difficulty presets belong to the embedded PushT"):
        generate_demos(1, task="PushTStandard", difficulty="easy")
