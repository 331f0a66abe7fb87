"""jepa_envs.datasets.hdf5: HDF5 writer, robomimic / LIBERO readers, cache and error messages."""
from __future__ import annotations

import json
import os

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jepa_envs.datasets.hdf5 import DatasetError, load_dataset, task_for_env_name, write_dataset


def _episodes(lengths=(5, 7, 3), size=16, seed=0):
    rng = np.random.default_rng(seed)
    return [{
        "obs": {"top_image": rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8),
                "agent_pos": rng.uniform(0, 512, (n, 2)).astype(np.float32)},
        "actions": rng.uniform(0, 512, (n, 2)).astype(np.float32),
        "states": rng.normal(size=(n, 5)),
        "rewards": rng.uniform(size=n).astype(np.float32),
        "dones": np.eye(n, dtype=np.uint8)[-1],
    } for n in lengths]


ENV_ARGS = {"env_name": "PushT", "type": "jepa_envs", "env_kwargs": {"image_size": 16}}


def test_round_trip_write_read(tmp_path):
    episodes = _episodes()
    path = tmp_path / "demos.hdf5"
    write_dataset(path, episodes, ENV_ARGS)
    with h5py.File(path, "r") as f:
        assert json.loads(f["data"].attrs["env_args"]) == ENV_ARGS
        assert f["data"].attrs["total"] == 15
        for i, ep in enumerate(episodes):
            g = f[f"data/demo_{i}"]
            assert g.attrs["num_samples"] == len(ep["actions"])
            for key in ("actions", "states", "rewards", "dones"):
                np.testing.assert_array_equal(g[key][()], ep[key])
    ds = load_dataset(path, cache_dir=False)
    assert ds.spec.name == "PushT" and ds.spec.image_size == 16 and ds.env_args == ENV_ARGS
    assert ds.num_episodes() == 3 and len(ds) == 15
    np.testing.assert_array_equal(ds.episode_ends, [5, 12, 15])
    assert ds.episode_ends.dtype == np.int64 and ds.actions.dtype == np.float32
    assert ds.obs["agent_pos"].dtype == np.float32 and ds.obs["top_image"].dtype == np.uint8
    for i, ep in enumerate(episodes):
        got = ds.episode(i)
        np.testing.assert_array_equal(got["actions"], ep["actions"])
        for key in ("top_image", "agent_pos"):
            np.testing.assert_array_equal(got["obs"][key], ep["obs"][key])
    assert ds.episode_slice(-1) == slice(12, 15)


def test_expert_demo_file_loads_and_resizes(pusht_demo_file):
    ds = load_dataset(pusht_demo_file, cache_dir=False)
    assert ds.num_episodes() == 4 and ds.obs["top_image"].shape[1:] == (84, 84, 3)
    assert ds.env_args["env_name"] == "PushT" and ds.env_args["env_kwargs"]["success_threshold"] > 0
    small = load_dataset(pusht_demo_file, image_size=42, cache_dir=False)
    assert small.obs["top_image"].shape == (len(ds), 42, 42, 3) and small.spec.image_size == 42
    # a 2x box downscale of the first frame agrees with the bilinear resize up to rounding at edges
    ref = ds.obs["top_image"][0].reshape(42, 2, 42, 2, 3).mean(axis=(1, 3))
    assert np.abs(ref - small.obs["top_image"][0]).mean() < 3.0


def test_cache_hit_is_used_and_invalidated_by_a_new_file(tmp_path):
    path = tmp_path / "demos.hdf5"
    write_dataset(path, _episodes(), ENV_ARGS)
    cache = tmp_path / "cache"
    first = load_dataset(path, cache_dir=cache)
    second = load_dataset(path, cache_dir=cache)
    assert not first.from_cache and second.from_cache
    assert isinstance(second.obs["top_image"], np.memmap)
    np.testing.assert_array_equal(second.obs["top_image"], first.obs["top_image"])
    np.testing.assert_array_equal(second.actions, first.actions)
    assert second.spec == first.spec and second.env_args == first.env_args
    write_dataset(path, _episodes(seed=1), ENV_ARGS)
    os.utime(path, ns=(1, 1))  # a different mtime even on coarse file systems
    third = load_dataset(path, cache_dir=cache)
    assert not third.from_cache
    assert not np.array_equal(third.actions, first.actions)
    assert len(list(cache.iterdir())) == 1  # the stale copy of the old file version is gone
    load_dataset(path, image_size=8, cache_dir=cache)
    assert len(list(cache.iterdir())) == 2  # another image size is another entry


def _write_libero(path, actions, control_delta, size=24, n=6):
    rng = np.random.default_rng(0)
    raw = {"agentview_rgb": rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8),
           "eye_in_hand_rgb": rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8),
           "ee_states": np.concatenate([rng.normal(size=(n, 3)), rng.normal(size=(n, 3))], axis=1),
           "gripper_states": rng.uniform(-0.04, 0.04, (n, 2)),
           "joint_states": rng.normal(size=(n, 7))}
    env_args = {"type": 1, "env_name": "Libero_Kitchen_Tabletop_Manipulation",
                "env_kwargs": {"controller_configs": {"type": "OSC_POSE", "control_delta": control_delta}}}
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["bddl_file_name"] = "libero/bddl_files/libero_10/KITCHEN_SCENE8_put_both_moka_pots_on_the_stove.bddl"
        data.attrs["env_args"] = json.dumps(env_args)
        data.attrs["problem_info"] = json.dumps({"language_instruction": "put both moka pots on the stove"})
        g = data.create_group("demo_0")
        for k, v in raw.items():
            g.create_dataset(f"obs/{k}", data=v)
        g.create_dataset("actions", data=actions)
    return raw


def test_libero_layout_maps_keys_orientation_and_actions(tmp_path):
    path = tmp_path / "libero.hdf5"
    rng = np.random.default_rng(1)
    actions = np.concatenate([rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), rng.choice([-1.0, 1.0], (6, 1))],
                             axis=1)
    raw = _write_libero(path, actions, control_delta=False)
    ds = load_dataset(path, cache_dir=False)
    assert ds.spec.name == "MokaMoka" and ds.spec.image_size == 24
    # LIBERO stores OpenGL frames: both cameras come out with their rows flipped, as the LIBERO env renders them
    from jepa_envs.tasks.robosuite_common import upright
    np.testing.assert_array_equal(ds.obs["agentview_image"], upright(raw["agentview_rgb"]))
    np.testing.assert_array_equal(ds.obs["robot0_eye_in_hand_image"], upright(raw["eye_in_hand_rgb"]))
    np.testing.assert_allclose(ds.obs["robot0_eef_pos"], raw["ee_states"][:, :3], rtol=1e-6)
    quat = Rotation.from_rotvec(raw["ee_states"][:, 3:]).as_quat()  # scipy: (x, y, z, w)
    got = ds.obs["robot0_eef_quat"].astype(np.float64)
    assert np.allclose(np.abs(np.sum(got * quat, axis=1)), 1.0, atol=1e-5)  # same rotation up to sign
    np.testing.assert_allclose(ds.obs["robot0_gripper_qpos"], raw["gripper_states"], rtol=1e-6)
    # absolute axis-angle actions -> position, first two rotation-matrix columns, gripper (Sec. 4.1)
    mats = Rotation.from_rotvec(actions[:, 3:6]).as_matrix()
    expected = np.concatenate([actions[:, :3], mats[:, :, 0], mats[:, :, 1], actions[:, 6:]], axis=1)
    np.testing.assert_allclose(ds.actions, expected, atol=1e-6)
    assert load_dataset(path, image_size=12, cache_dir=False).obs["agentview_image"].shape == (6, 12, 12, 3)


def test_delta_actions_are_refused_with_the_fix(tmp_path):
    path = tmp_path / "libero_delta.hdf5"
    _write_libero(path, np.zeros((6, 7)), control_delta=True)
    with pytest.raises(DatasetError, match="delta actions.*convert-abs-actions"):
        load_dataset(path, cache_dir=False)


def test_env_names_map_to_tasks():
    assert task_for_env_name("NutAssemblySquare").name == "Square"
    assert task_for_env_name("ToolHang").name == "ToolHang"
    assert task_for_env_name("TwoArmTransport").name == "Transport"
    assert task_for_env_name("Coffee_Preparation_D1").name == "CoffeePreparation"
    assert task_for_env_name("CoffeePreparation_D1").name == "CoffeePreparation"
    assert task_for_env_name("JEPA/PushT-v0").name == "PushT"
    assert task_for_env_name("Lift").name == "Lift" and task_for_env_name("PickPlaceCan").name == "Can"
    assert task_for_env_name("Stack") is None


def _good_file(path):
    write_dataset(path, _episodes(lengths=(4, 4)), ENV_ARGS)
    return path


def _edit(path, fn):
    with h5py.File(path, "a") as f:
        fn(f)


BAD_FILES = {
    "no data group": (lambda f: f.move("data", "other"), "no 'data' group"),
    "no demos": (lambda f: [f["data"].__delitem__(k) for k in list(f["data"])], "no demo_N groups"),
    "no env_args": (lambda f: f["data"].attrs.__delitem__("env_args"), "env_args'\\] is missing"),
    "bad json": (lambda f: f["data"].attrs.__setitem__("env_args", "{not json"), "not valid JSON"),
    "unknown env": (lambda f: f["data"].attrs.__setitem__("env_args", json.dumps({"env_name": "Stack"})),
                    "unknown env 'Stack'.*task="),
    "missing obs key": (lambda f: f["data/demo_1/obs"].__delitem__("agent_pos"),
                        "data/demo_1/obs has no 'agent_pos'"),
    "missing actions": (lambda f: f["data/demo_0"].__delitem__("actions"), "data/demo_0 has no 'actions'"),
    "short obs": (lambda f: (f["data/demo_1/obs"].__delitem__("agent_pos"),
                             f["data/demo_1/obs"].create_dataset("agent_pos", data=np.zeros((3, 2)))),
                  "demo_1/obs/agent_pos has 3 steps but actions have 4"),
    "wrong lowdim": (lambda f: (f["data/demo_0/obs"].__delitem__("agent_pos"),
                                f["data/demo_0/obs"].create_dataset("agent_pos", data=np.zeros((4, 3)))),
                     "expects agent_pos of shape \\(T, 2\\)"),
    "float images": (lambda f: (f["data/demo_0/obs"].__delitem__("top_image"),
                                f["data/demo_0/obs"].create_dataset("top_image", data=np.zeros((4, 16, 16, 3)))),
                     "must be uint8 \\(T, H, W, 3\\)"),
    "wrong action dim": (lambda f: (f["data/demo_1"].__delitem__("actions"),
                                    f["data/demo_1"].create_dataset("actions", data=np.zeros((4, 3)))),
                         "demo_1/actions has shape \\(4, 3\\)"),
    "mixed image sizes": (lambda f: (f["data/demo_1/obs"].__delitem__("top_image"),
                                     f["data/demo_1/obs"].create_dataset("top_image",
                                                                         data=np.zeros((4, 8, 8, 3), np.uint8))),
                          "pass image_size"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_files_raise_clear_errors(tmp_path, case):
    edit, message = BAD_FILES[case]
    path = _good_file(tmp_path / "bad.hdf5")
    _edit(path, edit)
    with pytest.raises(DatasetError, match=message) as err:
        load_dataset(path, cache_dir=tmp_path / "cache")
    assert str(path) in str(err.value)
    assert not list((tmp_path / "cache").glob("*"))  # nothing half-written is left in the cache


def test_missing_unreadable_and_mismatched_files(tmp_path):
    with pytest.raises(DatasetError, match="does not exist.*make-demos"):
        load_dataset(tmp_path / "nope.hdf5")
    text = tmp_path / "text.hdf5"
    text.write_text("not hdf5")
    with pytest.raises(DatasetError, match="not a readable HDF5 file"):
        load_dataset(text, cache_dir=False)
    path = _good_file(tmp_path / "good.hdf5")
    with pytest.raises(DatasetError, match="PushT dataset but task='Square'"):
        load_dataset(path, task="Square", cache_dir=False)
    with pytest.raises(DatasetError, match="unknown task 'Nope'"):
        load_dataset(path, task="Nope", cache_dir=False)


def test_write_dataset_validates_its_input(tmp_path):
    with pytest.raises(ValueError, match="env_name"):
        write_dataset(tmp_path / "x.hdf5", _episodes(), {"env_kwargs": {}})
    bad = _episodes()
    bad[1]["rewards"] = bad[1]["rewards"][:-1]
    with pytest.raises(ValueError, match="episode 1: rewards has 6 rows but actions have 7"):
        write_dataset(tmp_path / "x.hdf5", bad, ENV_ARGS)
    assert not list(tmp_path.glob("x.hdf5*"))
