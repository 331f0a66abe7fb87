"""scripts/robomimic_bcrnn.py's data path: the converted demonstrations are what robomimic's own training code reads
(its dataset, built by train.py's ``load_data_for_training`` from the script's config, returns the file's images,
proprioception and actions), and the evaluation's inverse mapping gives back the demonstrations' absolute actions.
The robomimic half runs in robomimic's venv (``make interop`` builds it) and is skipped where it is absent."""
import json
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

from jepa_envs.datasets.hdf5 import write_dataset
from script_loader import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "robomimic_bcrnn.py"


def _script():
    return load_script("robomimic_bcrnn")


def _demos(path: Path) -> Path:
    """Two short demonstrations in the pick job's layout: absolute position, 6-D rotation, gripper."""
    rng = np.random.default_rng(0)
    episodes = []
    for t in (12, 15):
        position = np.column_stack([rng.uniform(-0.1, 0.05, t), rng.uniform(-0.05, 0.06, t),
                                    rng.uniform(0.82, 1.05, t)])
        rest = np.column_stack([rng.uniform(-1, 1, (t, 6)), np.sign(rng.uniform(-1, 1, t))])
        episodes.append({"obs": {"agentview_image": rng.integers(0, 256, (t, 16, 16, 3), dtype=np.uint8),
                                 "robot0_eye_in_hand_image": rng.integers(0, 256, (t, 16, 16, 3), dtype=np.uint8),
                                 "robot0_eef_pos": rng.normal(size=(t, 3)).astype(np.float32),
                                 "robot0_eef_quat": rng.normal(size=(t, 4)).astype(np.float32),
                                 "robot0_gripper_qpos": rng.normal(size=(t, 2)).astype(np.float32)},
                         "actions": np.column_stack([position, rest]).astype(np.float32),
                         "rewards": np.zeros(t, np.float32), "dones": np.eye(1, t, t - 1, dtype=np.uint8)[0],
                         "attrs": {"seed": 0}})
    write_dataset(path, episodes, {"env_name": "Lift", "type": 1, "env_kwargs": {}})
    return path


def test_positions_fill_minus_one_to_one_and_the_evaluation_inverts_them(tmp_path):
    s = _script()
    out = s.convert(_demos(tmp_path / "ours.hdf5"), tmp_path / "robomimic.hdf5")
    with h5py.File(tmp_path / "ours.hdf5", "r") as src, h5py.File(out, "r") as dst:
        low, high = dst["data"].attrs["action_position_low"], dst["data"].attrs["action_position_high"]
        scaled = np.concatenate([dst[f"data/{d}/actions"][:] for d in ("demo_0", "demo_1")])
        ours = np.concatenate([src[f"data/{d}/actions"][:] for d in ("demo_0", "demo_1")])
        assert np.allclose(scaled[:, :3].min(axis=0), -1) and np.allclose(scaled[:, :3].max(axis=0), 1)
        assert np.array_equal(scaled[:, 3:], ours[:, 3:])    # rotation and gripper untouched
        assert np.allclose(s.unscale_position(scaled[:, :3], low, high), ours[:, :3], atol=1e-6)
        for key in src["data/demo_1/obs"]:
            assert np.array_equal(src[f"data/demo_1/obs/{key}"][:], dst[f"data/demo_1/obs/{key}"][:])
        assert dst["data/demo_1"].attrs["num_samples"] == 15


CHECK = """
import json, sys
import numpy as np
sys.path.insert(0, {scripts!r})
import robomimic_bcrnn as s
from robomimic.config import config_factory
import robomimic.utils.file_utils as FileUtils
import robomimic.utils.obs_utils as ObsUtils
import robomimic.utils.train_utils as TrainUtils
from pathlib import Path
s.write_config(Path({data!r}), Path({cfg!r}))
ext = json.load(open({cfg!r}))
config = config_factory(ext["algo_name"])
with config.values_unlocked():
    config.update(ext)
ObsUtils.initialize_obs_utils_with_config(config)
meta = FileUtils.get_shape_metadata_from_dataset(dataset_path=config.train.data, all_obs_keys=config.all_obs_keys)
trainset, validset = TrainUtils.load_data_for_training(config, obs_keys=meta["all_obs_keys"])
item = trainset[len(trainset) - 1]
print(json.dumps({{"len": len(trainset), "valid": validset is None, "shapes": meta["all_shapes"],
    "actions": item["actions"].tolist(), "image": item["obs"]["agentview_image"][0].tolist(),
    "eef": item["obs"]["robot0_eef_pos"].tolist()}}))
"""


@pytest.mark.skipif(not (ROOT / ".cache/interop/robomimic/bin/python").exists(),
                    reason="robomimic's venv is absent (make interop builds it)")
def test_robomimics_own_training_dataset_reads_the_converted_file(tmp_path):
    s = _script()
    out = s.convert(_demos(tmp_path / "ours.hdf5"), tmp_path / "robomimic.hdf5")
    code = CHECK.format(scripts=str(SCRIPT.parent), data=str(out), cfg=str(tmp_path / "config.json"))
    proc = subprocess.run([str(s.VENV_PYTHON), "-c", code], capture_output=True, text=True, timeout=300,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["len"] == 27 and got["valid"]                  # every step of both demonstrations, no validation
    assert got["shapes"]["agentview_image"] == [3, 16, 16]     # channels first, as robomimic's rgb modality stores
    with h5py.File(out, "r") as f:
        # the last sequence starts at demo_1's last step and is padded with it (seq_length 10, pad_seq_length)
        last = f["data/demo_1/actions"][-1]
        assert np.allclose(got["actions"], np.repeat(last[None], 10, axis=0))
        assert np.allclose(got["eef"], np.repeat(f["data/demo_1/obs/robot0_eef_pos"][-1][None], 10, axis=0))
        # the frame as stored (HWC uint8); robomimic's algorithm processes it (process_obs_dict: CHW, / 255) in
        # postprocess_batch_for_training, as the evaluation does before its RolloutPolicy
        assert np.array_equal(got["image"], f["data/demo_1/obs/agentview_image"][-1])
