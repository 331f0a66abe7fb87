"""LeRobot export: the v3.0 layout LeRobot reads (paths, features, parquet types, stats, the pandas task index)
and the files it refuses before writing anything. (LeRobot's own code reading these files is checked by
`make interop`, in a venv of its own.)"""
from __future__ import annotations

import json

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest

from jepa_envs.datasets.hdf5 import demo_names
from jepa_envs.datasets.lerobot import CODEBASE_VERSION, LeRobotError, export_lerobot, import_lerobot


def test_export_writes_lerobots_v3_layout(exported, pusht_demo_file):
    root, summary = exported
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == CODEBASE_VERSION == "v3.0" and info["fps"] == 10
    assert info["total_episodes"] == summary["episodes"] == 4 and info["splits"] == {"train": "0:4"}
    feats = info["features"]
    top = feats["observation.images.top"]
    assert top["dtype"] == "video" and top["shape"] == [84, 84, 3]
    assert feats["observation.images.top"]["info"]["video.codec"] == "h264"
    assert feats["observation.state"] == {"dtype": "float32", "shape": [2], "names": ["agent_pos[0]", "agent_pos[1]"]}
    assert {"timestamp", "frame_index", "episode_index", "index", "task_index", "action", "next.reward",
            "next.done", "observation.environment_state"} <= set(feats)
    for rel in ("data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet", "meta/tasks.parquet",
                "meta/stats.json", "videos/observation.images.top/chunk-000/file-000.mp4"):
        assert (root / rel).is_file(), rel
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert str(data.schema.field("observation.state").type) == "fixed_size_list<element: float>[2]"
    assert data.column("index").to_pylist() == list(range(info["total_frames"]))
    episodes = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [e["dataset_from_index"] for e in episodes][:2] == [0, episodes[0]["length"]]
    assert episodes[1]["videos/observation.images.top/from_timestamp"] == pytest.approx(episodes[0]["length"] / 10)
    tasks = pq.read_table(root / "meta/tasks.parquet")
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["__index_level_0__"]   # LeRobot's index
    stats = json.loads((root / "meta/stats.json").read_text())
    assert np.asarray(stats["observation.images.top"]["mean"]).shape == (3, 1, 1)
    assert {"min", "max", "mean", "std", "count", "q01", "q50", "q99"} <= set(stats["action"])
    with h5py.File(pusht_demo_file) as f:
        actions = np.concatenate([f["data"][n]["actions"][()] for n in demo_names(f["data"])])
    assert np.allclose(stats["action"]["mean"], actions.mean(0)) and stats["action"]["count"] == [len(actions)]


def test_export_refuses_a_file_without_images_or_an_existing_folder(pusht_demo_file, tmp_path):
    raw = tmp_path / "states_only.hdf5"
    with h5py.File(pusht_demo_file) as src, h5py.File(raw, "w") as dst:
        src.copy("data", dst)
        for n in demo_names(dst["data"]):
            del dst["data"][n]["obs"]["top_image"]
    with pytest.raises(LeRobotError, match="render it first: jepa-envs render-dataset"):
        export_lerobot(raw, tmp_path / "x")
    assert not (tmp_path / "x").exists() and not list(tmp_path.glob(".x.*"))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(LeRobotError, match="exists and is not empty"):
        export_lerobot(pusht_demo_file, tmp_path / "full")
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


def test_export_into_a_missing_parent_is_refused_before_any_work(pusht_demo_file, tmp_path):
    with pytest.raises(LeRobotError, match=r"a/b does not exist; create it first"):
        export_lerobot(pusht_demo_file, tmp_path / "a" / "b" / "out")
    assert not (tmp_path / "a").exists()


def test_a_reimported_dataset_keeps_its_rate_on_export(pusht_demo_file, tmp_path):
    """A 20 fps LeRobot root of a 10 Hz task, imported with its rate accepted, exports at 20 fps again (it was
    re-timed to the task's 10 silently), and another --fps is refused."""
    export_lerobot(pusht_demo_file, tmp_path / "at20", fps=20)
    import_lerobot(tmp_path / "at20", tmp_path / "back.hdf5", "PushT", fps=20)
    export_lerobot(tmp_path / "back.hdf5", tmp_path / "again")
    assert json.loads((tmp_path / "again/meta/info.json").read_text())["fps"] == 20
    with pytest.raises(LeRobotError, match=r"was recorded at 20 fps .* --fps 10 would re-time its frames"):
        export_lerobot(tmp_path / "back.hdf5", tmp_path / "at10", fps=10)
    assert not (tmp_path / "at10").exists()
