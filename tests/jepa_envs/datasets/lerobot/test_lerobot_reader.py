"""LeRobot import: a round trip that gives our arrays back, a root the trainer reads, and every bad dataset
refused in one line with nothing written. (LeRobot's own code writing datasets we import is checked by
`make interop`.)"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
from _lerobot_helpers import arrays, copy, edit_info, refused

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_envs.datasets.lerobot import KeyMap, LeRobotError, import_lerobot, open_lerobot, resolve_dataset
from jepa_envs.tasks.spec import get_task_spec


def test_round_trip_gives_the_arrays_back(exported, pusht_demo_file, tmp_path):
    root, _ = exported
    back = tmp_path / "back.hdf5"
    import_lerobot(root, back, "PushT")
    ours, theirs = arrays(pusht_demo_file), arrays(back)
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs):
        for key in ("actions", "states", "rewards", "dones", "obs/agent_pos", "obs/top_image"):
            assert np.array_equal(a[key], b[key]), key    # lossless video: frames bit-identical too
        assert b["task"] == "PushT"   # the task string every exported episode got
    demos = load_dataset(back, task="PushT", cache_dir=False)
    assert demos.episode_ends.tolist() == load_dataset(pusht_demo_file, cache_dir=False).episode_ends.tolist()


def test_train_reads_a_lerobot_root(exported, tmp_path, monkeypatch):
    monkeypatch.setenv("JEPA_DATA_CACHE", str(tmp_path / "cache"))
    root, _ = exported
    path = resolve_dataset(root, "PushT")
    assert path.suffix == ".hdf5" and resolve_dataset(root, "PushT") == path   # imported once, then reused
    assert len(load_dataset(path, task="PushT", cache_dir=False).episode_ends) == 4


def test_key_map_names_the_spec_keys():
    spec = get_task_spec("Square")
    km = KeyMap.parse(spec, ["observation.images.front=agentview_image", "observation.state="
                             "robot0_eef_pos,robot0_eef_quat,robot0_gripper_qpos", "actions=action"])
    assert km.images["observation.images.front"] == "agentview_image" and km.action == "actions"
    with pytest.raises(LeRobotError, match="is not a key of task Square"):
        KeyMap.parse(spec, ["observation.images.front=top_image"])


def test_another_codebase_version_is_refused(exported, tmp_path):
    root = copy(exported[0], tmp_path)
    edit_info(root, codebase_version="v2.1")
    refused(root, tmp_path, "LeRobotDataset v2.1.*convert_dataset_v21_to_v30")


def test_truncated_parquet_is_refused(exported, tmp_path):
    root = copy(exported[0], tmp_path)
    data = root / "data/chunk-000/file-000.parquet"
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    refused(root, tmp_path, "data/chunk-000/file-000.parquet is not a readable parquet file")


def test_missing_video_is_refused(exported, tmp_path):
    root = copy(exported[0], tmp_path)
    (root / "videos/observation.images.top/chunk-000/file-000.mp4").unlink()
    refused(root, tmp_path, "file-000.mp4 is missing")


def test_shape_disagreeing_with_info_is_refused(exported, tmp_path):
    root = copy(exported[0], tmp_path)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["observation.images.top"]["shape"] = [96, 96, 3]
    (root / "meta/info.json").write_text(json.dumps(info))
    refused(root, tmp_path, r"episode 0's frames are \[84, 84, 3\], info.json says \[96, 96, 3\]")


def test_missing_feature_and_fps_and_map_are_named(exported, tmp_path):
    root = exported[0]
    refused(root, tmp_path, "acts at 20 Hz; pass --fps 10", task="Square")
    refused(root, tmp_path, "no feature 'observation.images.agentview'", task="Square", fps=10)
    refused(root, tmp_path, "'actions'.*not a key|no feature 'act'", key_map=["act=action"])
    refused(root, tmp_path, "has shape \\[5\\]; task PushT's", key_map=["observation.environment_state=agent_pos"])


def test_a_dataset_with_embedded_png_images_imports(exported, tmp_path):
    """LeRobot's `image` features (PNG bytes in the data parquet) read as well as videos."""
    import io

    import pyarrow as pa
    from PIL import Image

    root = copy(exported[0], tmp_path)
    ds = open_lerobot(root)
    back = tmp_path / "video.hdf5"
    import_lerobot(root, back, "PushT")
    frames = np.concatenate([ep["obs/top_image"] for ep in arrays(back)])
    table = pq.read_table(root / "data/chunk-000/file-000.parquet")
    pngs = []
    for frame in frames:
        buf = io.BytesIO()
        Image.fromarray(frame).save(buf, format="PNG")
        pngs.append({"bytes": buf.getvalue(), "path": None})
    table = table.append_column("observation.images.top",
                                pa.array(pngs, pa.struct([("bytes", pa.binary()), ("path", pa.string())])))
    pq.write_table(table, root / "data/chunk-000/file-000.parquet")
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["observation.images.top"] = {"dtype": "image", "shape": [84, 84, 3],
                                                  "names": ["height", "width", "channels"]}
    info["video_path"] = None
    (root / "meta/info.json").write_text(json.dumps(info))
    shutil.rmtree(root / "videos")
    import_lerobot(root, tmp_path / "png.hdf5", "PushT")
    assert np.array_equal(np.concatenate([ep["obs/top_image"] for ep in arrays(tmp_path / "png.hdf5")]), frames)
    assert ds.fps == 10
