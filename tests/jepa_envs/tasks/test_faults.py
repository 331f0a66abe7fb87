"""Faults with a known onset (jepa_envs/tasks/faults.py): frames up to the onset untouched, the fault visible from
frame onset+1 as its formula says, the same seed the same episode."""
from __future__ import annotations

import zlib

import gymnasium as gym
import numpy as np
import pytest

from jepa_envs.tasks.fault_replay import IMAGE_FAULTS, FrameReplay, fault_frames
from jepa_envs.tasks.faults import (FAULTED_ENV, FAULTS, KINDS, ActionLatency, CameraShift, ColourShift, faults_for,
                                    wrap_fault)
from jepa_envs.tasks.pusht import COLORS
from jepa_envs.tasks.spec import get_task_spec

ONSET, STEPS, SIZE = 6, 14, 32
PUSHT_FAULTS = faults_for(get_task_spec("PushT"))   # Lift's and Can's own: tests/jepa_envs/tasks/test_pick_faults.py


def _push_actions(info):
    """Drive the agent through the block's centre, so that the block moves (dynamics faults show)."""
    x, y, _ = info["block_pose"]
    return np.array([x, y], np.float32)


def _run(env, seed, steps=STEPS):
    """Frames, agent positions and block poses of ``steps`` steps pushing the block, and the infos."""
    obs, info = env.reset(seed=seed)
    frames, infos = [obs], [info]
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(_push_actions(infos[-1]))
        frames.append(obs)
        infos.append(info)
        if terminated or truncated:
            break
    return frames, infos


def _clean(seed):
    return _run(gym.make("JEPA/PushT-v0", image_size=SIZE), seed)


def _faulted(name, seed, **kwargs):
    return _run(gym.make(FAULTED_ENV, fault=name, image_size=SIZE, fault_kwargs={"onset": ONSET, **kwargs}), seed)


def _same(a, b):
    return all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("name", PUSHT_FAULTS)
def test_frames_up_to_the_onset_are_untouched_and_the_fault_shows_after_it(name):
    clean, clean_info = _clean(5)
    faulted, infos = _faulted(name, 5)
    for j in range(ONSET + 1):
        assert _same(faulted[j], clean[j]), f"{name}: frame {j} <= onset {ONSET} changed"
    assert [i["fault_active"] for i in infos] == [False] * (ONSET + 1) + [True] * (len(infos) - ONSET - 1)
    assert all(i["fault_onset"] == ONSET and i["fault"] == name for i in infos)
    assert FAULTS[name].kind in KINDS
    later = [j for j in range(ONSET + 1, len(faulted)) if not _same(faulted[j], clean[j])
             or not np.allclose(infos[j]["block_pose"], clean_info[j]["block_pose"])]
    assert later, f"{name}: nothing changed after the onset"
    if FAULTS[name].kind in ("physical", "visual", "benign") or name == "action_noise":
        assert later[0] == ONSET + 1, f"{name}: first visible at frame {later[0]}, not {ONSET + 1}"


@pytest.mark.parametrize("name", PUSHT_FAULTS)
def test_the_same_seed_gives_the_same_episode(name):
    a, ai = _faulted(name, 11, onset=(2, 9))
    b, bi = _faulted(name, 11, onset=(2, 9))
    assert len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    assert [i["fault_onset"] for i in ai] == [i["fault_onset"] for i in bi]


def test_an_onset_range_is_drawn_from_the_seed():
    def onsets(seed):
        env = gym.make(FAULTED_ENV, fault="action_noise", image_size=SIZE, fault_kwargs={"onset": (5, 60)})
        return env.reset(seed=seed)[1]["fault_onset"]

    drawn = [onsets(s) for s in range(20)]
    assert drawn == [onsets(s) for s in range(20)]
    assert all(5 <= d <= 60 for d in drawn) and len(set(drawn)) > 5


def test_random_faults_differ_between_seeds():
    for name in ("block_displaced", "action_noise", "distractors"):
        a, _ = _faulted(name, 1)
        c, _ = _faulted(name, 2)
        clean_a, _ = _clean(1)
        clean_c, _ = _clean(2)
        delta_a = [f["top_image"].astype(int) - g["top_image"] for f, g in zip(a, clean_a)]
        delta_c = [f["top_image"].astype(int) - g["top_image"] for f, g in zip(c, clean_c)]
        assert any(not np.array_equal(x, y) for x, y in zip(delta_a, delta_c)), name


def test_visual_faults_follow_their_formulas():
    clean, _ = _clean(7)
    j = ONSET + 3
    shifted, _ = _faulted("colour_shift", 7, brightness=0.5, gains=(1.0, 2.0, 1.0))
    want = np.clip(clean[j]["top_image"].astype(np.float32) * np.array([0.5, 1.0, 0.5], np.float32), 0, 255)
    np.testing.assert_array_equal(shifted[j]["top_image"], want.round().astype(np.uint8))

    moved, _ = _faulted("camera_shift", 7, pixels=2)
    env = CameraShift(gym.make("JEPA/PushT-v0", image_size=SIZE), onset=ONSET, pixels=2)
    env.reset(seed=7)
    dy, dx = env.shift
    image, got = clean[j]["top_image"], moved[j]["top_image"]
    inner = got[max(dy, 0):SIZE + min(dy, 0), max(dx, 0):SIZE + min(dx, 0)]
    np.testing.assert_array_equal(inner, image[max(-dy, 0):SIZE + min(-dy, 0), max(-dx, 0):SIZE + min(-dx, 0)])

    tinted, _ = _faulted("background_tint", 7, tint=(-20, 0, 20))
    background = np.all(clean[j]["top_image"] == np.array(COLORS["background"], np.uint8), axis=-1)
    assert background.mean() > 0.5
    np.testing.assert_array_equal(tinted[j]["top_image"][~background], clean[j]["top_image"][~background])
    assert (tinted[j]["top_image"][background] == np.array(COLORS["background"]) + [-20, 0, 20]).all()


def test_sensor_noise_is_the_seeded_gaussian_of_its_std():
    """Each noisy frame is the clean frame plus N(0, std) per pixel, rounded and clipped; frame j's draws come
    from a generator of (seed, j, camera) alone."""
    clean, _ = _clean(7)
    noisy, _ = _faulted("sensor_noise", 7, std=6.0)
    residuals = []
    for j in range(ONSET + 1, len(noisy)):
        frame = clean[j]["top_image"]
        rng = np.random.default_rng([7, FAULTS["sensor_noise"].wrapper.salt, j, zlib.crc32(b"top_image")])
        want = np.clip(np.rint(frame.astype(np.float64) + rng.normal(0.0, 6.0, frame.shape)), 0, 255)
        np.testing.assert_array_equal(noisy[j]["top_image"], want.astype(np.uint8))
        inside = (frame > 30) & (frame < 225)                       # away from the clip
        residuals.append((noisy[j]["top_image"].astype(float) - frame)[inside])
    residuals = np.concatenate(residuals)
    assert abs(residuals.mean()) < 0.2 and abs(residuals.std() - np.sqrt(36 + 1 / 12)) < 0.3


def test_latency_executes_the_action_given_n_steps_earlier():
    actions = np.random.default_rng(0).uniform(100, 400, size=(STEPS, 2)).astype(np.float32)
    env = ActionLatency(gym.make("JEPA/PushT-v0", image_size=SIZE), onset=ONSET, steps=3)
    executed = []
    inner_step = env.env.step
    env.env.step = lambda a: (executed.append(np.array(a)), inner_step(a))[1]
    env.reset(seed=0)
    for a in actions:
        env.step(a)
    want = [actions[i] if i < ONSET else actions[i - 3] for i in range(STEPS)]
    np.testing.assert_array_equal(np.stack(executed), np.stack(want))


def test_dynamics_faults_change_the_simulation_at_the_onset_step():
    for name, read in (("block_friction", lambda s: [shape.friction for shape in s.block.shapes]),
                       ("block_slides", lambda s: s.space.damping), ("weak_actuator", lambda s: (s.kp, s.kv))):
        env = gym.make(FAULTED_ENV, fault=name, image_size=SIZE, fault_kwargs={"onset": ONSET})
        env.reset(seed=0)
        sim = env.unwrapped.backend
        before = read(sim)
        for t in range(ONSET):
            env.step(np.array([100, 100], np.float32))
            assert read(sim) == before, f"{name} changed at step {t} < onset"
        env.step(np.array([100, 100], np.float32))
        assert read(sim) != before, name
    sim = env.unwrapped.backend
    assert (sim.kp, sim.kv) == (50.0, 10.0)   # halved


def test_bad_options_are_refused_with_the_fix():
    base = gym.make("JEPA/PushT-v0", image_size=SIZE)
    with pytest.raises(ValueError, match="unknown fault 'smoke'; choose one of"):
        wrap_fault(base, "smoke")
    with pytest.raises(ValueError, match="its options are onset and those of ActionNoise"):
        wrap_fault(base, "action_noise", sigma=3)
    with pytest.raises(ValueError, match="onset must be >= 0"):
        wrap_fault(base, "action_noise", onset=-1)
    with pytest.raises(ValueError, match="needs JEPA/PushT-v0"):
        wrap_fault(_OtherTask(), "weak_actuator")
    wrap_fault(_OtherTask(), "action_noise")   # actuation and visual faults work on any task


class _OtherTask(gym.Env):
    observation_space = gym.spaces.Box(0, 1, (1,))
    action_space = gym.spaces.Box(0, 1, (1,))


def test_colour_shift_refuses_bad_gains():
    with pytest.raises(ValueError, match="three positive channel gains"):
        ColourShift(gym.make("JEPA/PushT-v0", image_size=SIZE), gains=(1, 1))


def test_sensor_noise_of_a_frame_does_not_depend_on_which_frames_were_rendered():
    """Under RenderOnDemand (3 of every 8 frames rendered) frame j's noise is the all-frames run's: with one running
    generator the skipped frames' draws were missing and frames 7, 8, 12 ... differed for the same seed."""
    from jepa_envs.tasks.wrappers import RenderOnDemand

    every, _ = _faulted("sensor_noise", 9)
    demand = RenderOnDemand(gym.make(FAULTED_ENV, fault="sensor_noise", image_size=SIZE,
                                     fault_kwargs={"onset": ONSET}), decision_every=8, obs_steps=2, future_k=4)
    sparse, infos = _run(demand, 9)
    rendered = [j for j in range(ONSET + 1, len(sparse)) if j == 0 or infos[j].get("images_rendered")]
    assert rendered == [7, 8, 12]
    for j in rendered:
        assert _same(sparse[j], every[j]), f"frame {j}"


def test_sensor_noise_draws_share_the_frames_up_to_the_onset_and_differ_after_it():
    """``draw``: draw 0 is the default sequence; another draw is the same seeded generator's key plus the draw (its
    formula), the same for the same draw, and every draw leaves the frames up to the onset as they were."""
    base, _ = _faulted("sensor_noise", 7)
    zero, _ = _faulted("sensor_noise", 7, draw=0)
    one, _ = _faulted("sensor_noise", 7, draw=1)
    again, _ = _faulted("sensor_noise", 7, draw=1)
    two, _ = _faulted("sensor_noise", 7, draw=2)
    clean, _ = _clean(7)
    for j in range(len(base)):
        assert _same(zero[j], base[j]) and _same(one[j], again[j])
        if j <= ONSET:
            assert _same(one[j], clean[j]) and _same(two[j], clean[j])
        else:
            assert not _same(one[j], base[j]) and not _same(one[j], two[j])
            rng = np.random.default_rng([7, FAULTS["sensor_noise"].wrapper.salt, j, zlib.crc32(b"top_image"), 1])
            frame = clean[j]["top_image"]
            want = np.clip(np.rint(frame.astype(np.float64) + rng.normal(0.0, 4.0, frame.shape)), 0, 255)
            np.testing.assert_array_equal(one[j]["top_image"], want.astype(np.uint8))
    for bad in (-1, 1.5, True, "1"):
        with pytest.raises(ValueError, match="draw must be an integer"):
            _faulted("sensor_noise", 7, draw=bad)


@pytest.mark.parametrize("name", IMAGE_FAULTS)
@pytest.mark.parametrize("seed", [3, 8])
def test_recorded_frames_show_an_image_fault_as_a_live_episode_does(name, seed):
    """fault_frames on a clean episode's recorded frames gives, image for image, what the live faulted episode of
    the same seed showed after the onset (the per-episode draws, the step-keyed noise, PushT's plain background)."""
    clean, _ = _clean(seed)
    live, _ = _faulted(name, seed)
    shown = fault_frames(get_task_spec("PushT"), clean[ONSET + 1:], name, seed, first_step=ONSET + 1)
    assert len(shown) == len(live) - ONSET - 1
    for j, frame in enumerate(shown):
        assert _same(frame, live[ONSET + 1 + j]), f"{name}: recorded frame {ONSET + 1 + j} differs from the live one"
    assert not _same(shown[0], clean[ONSET + 1])


@pytest.mark.parametrize("name", IMAGE_FAULTS)
def test_recorded_standard_pusht_frames_match_a_live_episode(name):
    """The same on gym-pusht's task (its own renderer; the tint offsets the whole image there, live and replayed)."""
    env_id, onset = "JEPA/PushTStandard-v0", 3
    clean, _ = _run(gym.make(env_id, image_size=SIZE), 4, steps=8)
    live, _ = _run(gym.make(FAULTED_ENV, base=env_id, fault=name, image_size=SIZE,
                            fault_kwargs={"onset": onset}), 4, steps=8)
    shown = fault_frames(get_task_spec("PushTStandard"), clean[onset + 1:], name, 4, first_step=onset + 1)
    assert all(_same(a, b) for a, b in zip(shown, live[onset + 1:])) and len(shown) == len(live) - onset - 1


def test_the_tint_offsets_every_pixel_of_frames_not_rendered_by_pushts_own_env():
    """FrameReplay masks the background only for PushT's frames; Lift's are offset whole, as BackgroundTint does
    live on robosuite (a frame full of PushT's background colour makes a mask-everywhere bug visible)."""
    spec = get_task_spec("Lift")
    rng = np.random.default_rng(0)
    frame = {k: rng.integers(0, 256, (8, 8, 3), dtype=np.uint8) for k in spec.image_keys}
    frame[spec.image_keys[0]][:4] = COLORS["background"]
    shown = fault_frames(spec, [frame], "background_tint", 0)[0]
    for k in spec.image_keys:
        expected = np.clip(frame[k].astype(np.int16) + np.array([-12, -4, 10]), 0, 255).astype(np.uint8)
        assert np.array_equal(shown[k], expected), k


def test_fault_frames_refuses_what_needs_a_live_episode():
    spec = get_task_spec("PushT")
    clean, _ = _clean(1)
    assert set(IMAGE_FAULTS) == {"background_tint", "camera_shift", "colour_shift", "distractors", "sensor_noise"}
    for name in ("block_displaced", "action_latency", "light_dimmed"):
        with pytest.raises(ValueError, match=f"{name} changes the .* of a live episode.*jepa-policy eval --faults"):
            fault_frames(spec, clean, name, 0)
    with pytest.raises(ValueError, match="unknown fault 'nope'"):
        fault_frames(spec, clean, "nope", 0)
    with pytest.raises(ValueError, match="first_step must be >= 1"):
        fault_frames(spec, clean, "camera_shift", 0, first_step=0)
    with pytest.raises(ValueError, match="sets camera_shift's onset itself.*drop onset="):
        fault_frames(spec, clean, "camera_shift", 0, onset=4)
    with pytest.raises(KeyError, match="lack"):
        FrameReplay(spec, [{"state": np.zeros(2)}])
    replay = FrameReplay(spec, clean[:2])
    replay.reset()
    replay.step(None)
    with pytest.raises(RuntimeError, match="only 2 frames; reset it"):
        replay.step(None)
