"""Render-on-demand schedule, video recording and vector envs on JEPA/PushT-v0."""
from __future__ import annotations

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np
import pytest

import jepa_envs  # noqa: F401  (registers the ids)
from jepa_envs.tasks.wrappers import RecordEpisodeVideo, RenderOnDemand, render_schedule

ACTIONS = np.random.default_rng(0).uniform(100, 400, size=(24, 2)).astype(np.float32)


def test_schedule_has_history_and_future_frames():
    # n = 8 actions per chunk, 2 history frames, future frame k = 4 after each decision
    assert render_schedule(25, 8, 2, 4) == [0, 4, 7, 8, 12, 15, 16, 20, 23, 24]
    assert render_schedule(17, 8, 2, 0) == [0, 7, 8, 15, 16]
    assert render_schedule(12, 4, 1, 6) == [0, 4, 6, 8, 10]


def test_render_on_demand_renders_exactly_the_scheduled_frames():
    plain = gym.make("JEPA/PushT-v0")
    wrapped = RenderOnDemand(gym.make("JEPA/PushT-v0"))
    assert (wrapped.decision_every, wrapped.obs_steps, wrapped.future_k) == (8, 2, 4)  # from the task spec
    ref, _ = plain.reset(seed=5)
    obs, info = wrapped.reset(seed=5)
    assert info["images_rendered"]
    np.testing.assert_array_equal(obs["top_image"], ref["top_image"])
    rendered = []
    for j, action in enumerate(ACTIONS, start=1):
        ref, *_ = plain.step(action)
        obs, _, _, _, info = wrapped.step(action)
        np.testing.assert_array_equal(obs["agent_pos"], ref["agent_pos"])  # low-dim always there
        if info["images_rendered"]:
            rendered.append(j)
            np.testing.assert_array_equal(obs["top_image"], ref["top_image"])
        else:
            assert not obs["top_image"].any()
    assert rendered == render_schedule(25, 8, 2, 4)[1:]
    # a new episode restarts the schedule
    _, info = wrapped.reset(seed=6)
    assert info["images_rendered"] and wrapped.frame == 0
    plain.close()
    wrapped.close()


def test_render_on_demand_rejects_other_envs_and_bad_settings():
    with pytest.raises(TypeError, match="needs a jepa_envs env"):
        RenderOnDemand(gym.make("CartPole-v1"))
    with pytest.raises(ValueError, match="decision_every and obs_steps must be >= 1"):
        RenderOnDemand(gym.make("JEPA/PushT-v0"), decision_every=0)


def test_video_records_one_gif_per_episode(tmp_path):
    env = RecordEpisodeVideo(gym.make("JEPA/PushT-v0", image_size=32, max_episode_steps=6), tmp_path)
    for seed in (0, 1):
        env.reset(seed=seed)
        for action in ACTIONS[:6]:
            *_, truncated, _ = env.step(action)
        assert truncated
    env.close()
    assert [p.name for p in env.paths] == ["episode-0.gif", "episode-1.gif"]
    frames = imageio.mimread(env.paths[0])
    assert len(frames) == 7 and frames[0].shape[:2] == (32, 32)


def test_video_under_render_on_demand_keeps_only_rendered_frames(tmp_path):
    env = RecordEpisodeVideo(RenderOnDemand(gym.make("JEPA/PushT-v0", image_size=32)), tmp_path)
    env.reset(seed=0)
    for action in ACTIONS[:16]:
        env.step(action)
    env.close()
    assert len(imageio.mimread(env.paths[0])) == len(render_schedule(17, 8, 2, 4))


def test_video_mp4_from_render(tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason="mp4 needs the optional imageio-ffmpeg package")
    env = RecordEpisodeVideo(gym.make("JEPA/PushT-v0", render_mode="rgb_array", render_size=64), tmp_path,
                             format="mp4", source="render")
    env.reset(seed=0)
    for action in ACTIONS[:5]:
        env.step(action)
    env.close()
    reader = imageio.get_reader(env.paths[0])
    frames = [f for f in reader]
    reader.close()
    assert len(frames) == 6 and frames[0].shape == (64, 64, 3)


def test_video_rejects_bad_settings(tmp_path):
    with pytest.raises(ValueError, match="format must be"):
        RecordEpisodeVideo(gym.make("JEPA/PushT-v0"), tmp_path, format="avi")
    with pytest.raises(ValueError, match="render_mode='rgb_array'"):
        RecordEpisodeVideo(gym.make("JEPA/PushT-v0"), tmp_path, source="render")


def _make(image_size=32):
    return lambda: gym.make("JEPA/PushT-v0", image_size=image_size)


@pytest.mark.parametrize("vector_cls", [gym.vector.SyncVectorEnv, gym.vector.AsyncVectorEnv])
def test_vector_envs_match_single_envs(vector_cls):
    envs = vector_cls([_make(), _make()])
    single = gym.make("JEPA/PushT-v0", image_size=32)
    obs, info = envs.reset(seed=[11, 12])
    ref, _ = single.reset(seed=12)
    assert obs["top_image"].shape == (2, 32, 32, 3) and obs["agent_pos"].shape == (2, 2)
    np.testing.assert_array_equal(obs["top_image"][1], ref["top_image"])
    for action in ACTIONS[:5]:
        obs, reward, terminated, truncated, info = envs.step(np.stack([action, action]))
        ref, ref_reward, *_ = single.step(action)
    np.testing.assert_array_equal(obs["top_image"][1], ref["top_image"])
    assert reward[1] == pytest.approx(ref_reward) and info["is_success"].shape == (2,)
    envs.call("set_render_images", False)
    obs, *_ = envs.step(np.stack([ACTIONS[0], ACTIONS[0]]))
    assert not obs["top_image"].any() and obs["agent_pos"].any()
    envs.close()
    single.close()
