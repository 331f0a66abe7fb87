"""render-dataset: recorded states re-render to the frames rendered live; raw files no one here wrote (robosuite's
shipped Lift demonstrations) render, load through our loader and replay to success in JEPA/Lift-v0."""
from __future__ import annotations

import json
import os

import gymnasium as gym
import h5py
import numpy as np
import pytest

import jepa_envs  # noqa: F401  registers the ids
from jepa_envs.datasets.hdf5 import DatasetError, load_dataset
from jepa_envs.datasets.render_dataset import render_dataset, replay_in_env
from jepa_envs.tasks.spec import get_task_spec


def _raw_file(path, env_args, episodes, first: int = 0):
    """A raw dataset as robomimic stores one before dataset_states_to_obs: states and actions only (demo_<first>,
    demo_<first + 1>, ...)."""
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps(env_args)
        for i, ep in enumerate(episodes, first):
            g = data.create_group(f"demo_{i}")
            g.create_dataset("states", data=ep["states"])
            g.create_dataset("actions", data=ep["actions"])
            if "model" in ep:
                g.attrs["model_file"] = ep["model"]
    return path


def test_pusht_states_re_render_to_the_live_frames(tmp_path):
    env = gym.make("JEPA/PushT-v0").unwrapped
    rng = np.random.default_rng(0)
    episodes, live = [], []
    for seed in (1, 2):
        obs, _ = env.reset(seed=seed)
        states, actions, frames = [], [], []
        for _ in range(12):
            states.append(env.get_state())
            frames.append(obs["top_image"])
            action = np.clip(obs["agent_pos"] + rng.normal(0, 30, 2), 0, 512).astype(np.float32)
            actions.append(action)
            obs, *_ = env.step(action)
        episodes.append({"states": np.array(states), "actions": np.array(actions)})
        live.append(np.array(frames))
    env.close()
    raw = _raw_file(tmp_path / "raw.hdf5", {"env_name": "PushT", "type": "jepa_envs", "env_kwargs": {}}, episodes)
    report = render_dataset(raw, tmp_path / "out.hdf5")
    assert [e["state_error"] for e in report["episodes"]] == [0.0, 0.0]
    assert all(e["replay_drift"] < 1e-6 for e in report["episodes"]), "PushT replays its actions exactly"
    with h5py.File(tmp_path / "out.hdf5") as f:
        for i, frames in enumerate(live):
            assert np.array_equal(f[f"data/demo_{i}/obs/top_image"][()], frames)
            assert np.array_equal(f[f"data/demo_{i}/actions"][()], episodes[i]["actions"])
    assert len(load_dataset(tmp_path / "out.hdf5", cache_dir=False).episode_ends) == 2


def test_episodes_keep_their_names_and_the_bar_goes_to_stderr(tmp_path, capsys):
    """A file of demo_1..demo_3 (robomimic files skip numbers; their masks name demos) was written as
    demo_0..demo_2 without a word; the names are kept now. The bar is on stderr, off with progress=False."""
    env = gym.make("JEPA/PushT-v0").unwrapped
    episodes = []
    for seed in (1, 2, 3):
        env.reset(seed=seed)
        states = [env.get_state()]
        actions = [np.full(2, 256.0, np.float32)] * 3
        for action in actions[:-1]:
            env.step(action)
            states.append(env.get_state())
        episodes.append({"states": np.array(states), "actions": np.array(actions)})
    env.close()
    raw = _raw_file(tmp_path / "raw.hdf5", {"env_name": "PushT", "type": "jepa_envs", "env_kwargs": {}}, episodes,
                    first=1)
    report = render_dataset(raw, tmp_path / "out.hdf5", progress=True)
    out, err = capsys.readouterr()
    assert [e["demo"] for e in report["episodes"]] == ["demo_1", "demo_2", "demo_3"]
    with h5py.File(tmp_path / "out.hdf5") as f:
        assert sorted(f["data"]) == ["demo_1", "demo_2", "demo_3"]
        assert np.array_equal(f["data/demo_2/states"][()], episodes[1]["states"])
    assert out == "" and "render-dataset: 100%" in err and "3/3" in err
    render_dataset(raw, tmp_path / "quiet.hdf5", progress=False)
    assert capsys.readouterr() == ("", "")


def test_a_file_without_states_or_environment_is_refused(tmp_path):
    path = tmp_path / "no_states.hdf5"
    with h5py.File(path, "w") as f:
        g = f.create_group("data")
        g.attrs["env_args"] = json.dumps({"env_name": "PushT"})
        g.create_group("demo_0").create_dataset("actions", data=np.zeros((3, 2)))
    with pytest.raises(DatasetError, match="data/demo_0 has no 'states'; render-dataset replays"):
        render_dataset(path, tmp_path / "out.hdf5")
    with h5py.File(path, "a") as f:
        f["data/demo_0"].create_dataset("states", data=np.zeros((3, 5)))
        del f["data"].attrs["env_args"]
    with pytest.raises(DatasetError, match="neither env_args .* nor env_info"):
        render_dataset(path, tmp_path / "out.hdf5")
    assert not (tmp_path / "out.hdf5").exists()


robosuite = pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")


def _record_and_re_render(tmp_path, task, detect_task=False):
    """A rollout of ``task`` recorded as robomimic / MimicGen record one (model XML, states, absolute actions),
    rendered again from the states: every frame must be array-equal to the one rendered live."""
    spec = get_task_spec(task)
    keys = [f"{camera}_image" for camera in spec.cameras]
    env = gym.make(f"JEPA/{task}-v0", image_size=32).unwrapped
    env.reset(seed=3)
    # the rollout runs in the model as stored (MJCF text keeps fewer digits than the model built in Python: the
    # cube's randomised size would differ in its last digits), as robomimic's recorded episodes do
    model = env.backend.sim.model.get_xml()
    obs, _ = env.reset(seed=3, options={"model": model, "state": env.backend.sim.get_state().flatten()})
    rng = np.random.default_rng(1)
    states, actions, frames = [], [], []
    for _ in range(8):
        states.append(env.backend.sim.get_state().flatten())
        frames.append({k: obs[k] for k in keys})
        action = env.hold_action()
        action[:3] += rng.normal(0, 0.01, 3)
        actions.append(action)
        obs, *_ = env.step(action)
    env_args = env.env_args
    env.close()
    raw = _raw_file(tmp_path / "raw.hdf5", env_args, [{"states": np.array(states), "actions": np.array(actions),
                                                       "model": model}])
    report = render_dataset(raw, tmp_path / "out.hdf5", task=None if detect_task else task, size=32)
    episode = report["episodes"][0]
    assert episode["model"] == "recorded" and episode["state_error"] == 0.0
    with h5py.File(tmp_path / "out.hdf5") as f:
        for key in keys:
            assert np.array_equal(f[f"data/demo_0/obs/{key}"][()], np.stack([fr[key] for fr in frames])), key
        assert np.allclose(f["data/demo_0/actions"][()], np.array(actions), atol=1e-6)


@pytest.mark.robosuite
def test_lift_states_re_render_to_the_live_frames(tmp_path):
    """Our own Lift rollout recorded as robomimic records one: rendered again from the states, every frame of
    both cameras is array-equal to the frame rendered live."""
    _record_and_re_render(tmp_path, "Lift")


@pytest.mark.robosuite
@pytest.mark.parametrize("task", ["ThreePieceAssembly", "CoffeePreparation"])
def test_mimicgen_states_re_render_to_the_live_frames(tmp_path, task):
    """A MimicGen D1 rollout recorded as MimicGen's generated datasets store it (env_args naming the MimicGen env,
    model XML, states): the task is found from env_args alone and every frame re-renders array-equal. Runs where
    MimicGen is installed (`jepa-envs install-mimicgen CLONE`); MimicGen is not on PyPI."""
    pytest.importorskip("mimicgen", reason="MimicGen is not installed (jepa-envs install-mimicgen CLONE)")
    _record_and_re_render(tmp_path, task, detect_task=True)


@pytest.mark.robosuite
@pytest.mark.slow
def test_robosuites_shipped_lift_demonstration_renders_loads_and_replays(tmp_path):
    """Data no one here wrote: robosuite's own Lift demonstration (states + delta actions, an older robosuite's
    model XML). Rendered, converted to absolute actions, read by the training loader and replayed open-loop in
    JEPA/Lift-v0 from its recorded start: it lifts the cube."""
    src = os.path.join(os.path.dirname(robosuite.__file__), "models/assets/demonstrations/lift/demo.hdf5")
    one = tmp_path / "lift_demo3.hdf5"
    with h5py.File(src) as f, h5py.File(one, "w") as g:
        data = g.create_group("data")
        for key, value in f["data"].attrs.items():
            data.attrs[key] = value
        f.copy(f["data/demo_3"], data, name="demo_0")   # 392 steps: the shortest of the three
    # 32 px without the table's reflection: the frames' content is checked below and by render-dataset itself;
    # here the conversion, the loader and the replay are (84 px with the reflection cost 10x the time)
    report = render_dataset(one, tmp_path / "lift.hdf5", task="Lift", size=32, reflections=False)
    episode = report["episodes"][0]
    assert episode["state_error"] == 0.0 and episode["model"].startswith("own")   # another robosuite's geometry
    assert episode["replay_success"]
    demos = load_dataset(tmp_path / "lift.hdf5", task="Lift", cache_dir=False)
    assert demos.actions.shape == (392, 10) and demos.obs["agentview_image"].shape == (392, 32, 32, 3)
    replay = replay_in_env(tmp_path / "lift.hdf5", "Lift")
    assert replay["successes"] == 1 and replay["episodes"][0]["within_time_limit"]


def _shipped_lift_demo(tmp_path, steps):
    """The first ``steps`` of robosuite's own Lift demonstration 3 (robosuite 1.4.0's model XML, which this
    robosuite cannot load), as a raw file."""
    src = os.path.join(os.path.dirname(robosuite.__file__), "models/assets/demonstrations/lift/demo.hdf5")
    one = tmp_path / "lift_cut.hdf5"
    with h5py.File(src) as f, h5py.File(one, "w") as g:
        data = g.create_group("data")
        for key, value in f["data"].attrs.items():
            data.attrs[key] = value
        demo = data.create_group("demo_0")
        demo.attrs["model_file"] = f["data/demo_3"].attrs["model_file"]
        for key in ("states", "actions"):
            demo.create_dataset(key, data=f["data/demo_3"][key][:steps])
    return one


def _live_frames(task, states, size, cube_size=None):
    """Each state rendered live by a freshly made env of the task (the content every written frame must have),
    its cube resized to ``cube_size`` by editing the task's own XML here (the size the recording drew)."""
    env = gym.make(f"JEPA/{task}-v0", image_size=size).unwrapped
    try:
        options = {"state": states[0]}
        if cube_size is not None:
            xml = env.backend.sim.model.get_xml()
            for name in ("cube_g0", "cube_g0_vis"):
                start = xml.index(f'name="{name}"')
                at = xml.index('size="', start) + len('size="')
                xml = xml[:at] + cube_size + xml[xml.index('"', at):]
            options["model"] = xml
        env.reset(seed=0, options=options)
        frames = []
        for state in states:
            env.set_sim_state(state)
            frames.append(env.observe_now())
    finally:
        env.close()
    return frames


def _recorded_cube_size(raw):
    with h5py.File(raw) as f:
        xml = f["data/demo_0"].attrs["model_file"]
    geom = xml[xml.index('<geom name="cube_g0"'):]
    return geom[geom.index('size="') + 6:].split('"')[0]


@pytest.mark.robosuite
def test_robosuites_shipped_lift_demo_renders_the_scene_of_its_states(tmp_path):
    """robosuite 1.4.0's XML fails to load here and the task's own model takes over: every written frame must be
    the live render of its state (it was all black or noise: the failed load's render context, freed late, took
    the new context's GL buffers with it)."""
    raw = _shipped_lift_demo(tmp_path, steps=4)
    report = render_dataset(raw, tmp_path / "out.hdf5", task="Lift", size=32)
    model = report["episodes"][0]["model"]
    assert model.startswith("own") and "2 geoms sized as recorded: cube_g0, cube_g0_vis" in model
    with h5py.File(raw) as f:
        states = f["data/demo_0/states"][()]
    cube = _recorded_cube_size(raw)
    assert cube == "0.0208459 0.0202324 0.020821"   # robosuite 1.4.0's draw, smaller than this task's own cube
    live = _live_frames("Lift", states, 32, cube_size=cube)
    assert not np.array_equal(live[0]["agentview_image"],
                              _live_frames("Lift", states[:1], 32)[0]["agentview_image"])   # the size shows
    with h5py.File(tmp_path / "out.hdf5") as f:
        for camera in ("agentview_image", "robot0_eye_in_hand_image"):
            written = f[f"data/demo_0/obs/{camera}"][()]
            assert written.std() > 10, f"{camera}: a flat frame is no scene"
            for t, frame in enumerate(live):
                assert np.array_equal(written[t], frame[camera]), (camera, t)


@pytest.mark.robosuite
def test_a_frame_unlike_the_live_render_is_never_written(tmp_path, monkeypatch):
    """Fault injection, the mechanism of the black frames: another render context, freed while the renderer's is
    current, deletes the renderer's GL buffers by id. render-dataset must refuse the episode, naming it, and
    write nothing."""
    import gc

    from robosuite.utils.binding_utils import MjRenderContextOffscreen, MjSim

    from jepa_envs.datasets.render_dataset import RobosuiteRenderer

    reset_to = RobosuiteRenderer._reset_to

    def reset_then_lose_buffers(self, states, model):
        which = reset_to(self, states, model)
        scratch = MjSim.from_xml_string(self.env.backend.sim.model.get_xml())
        MjRenderContextOffscreen(scratch, device_id=-1)    # a second GL context, made current
        self.env._make_gl_current()
        del scratch._render_context_offscreen, scratch
        gc.collect()                                       # freed now, with the renderer's context current
        return which

    monkeypatch.setattr(RobosuiteRenderer, "_reset_to", reset_then_lose_buffers)
    raw = _shipped_lift_demo(tmp_path, steps=3)
    with pytest.raises(DatasetError, match=r"demo_0.*frame 0 .* is not the live render of its state"):
        render_dataset(raw, tmp_path / "out.hdf5", task="Lift", size=32)
    assert not (tmp_path / "out.hdf5").exists() and not list(tmp_path.glob("out.hdf5*"))
