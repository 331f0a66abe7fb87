"""LeRobot import: a round trip that gives our arrays back, a root the trainer reads, and every bad dataset
refused in one line with nothing written. (LeRobot's own code writing datasets we import is checked by
`make interop`.)"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
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


# ----------------------------------------------------------------------------- what import says


def _add_feature(root, key, values, ft):
    table = pq.read_table(root / "data/chunk-000/file-000.parquet")
    column = pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])
    pq.write_table(table.append_column(key, column), root / "data/chunk-000/file-000.parquet")
    info = json.loads((root / "meta/info.json").read_text())
    info["features"][key] = ft
    (root / "meta/info.json").write_text(json.dumps(info))


def test_unmapped_features_are_listed_with_how_to_map_them(exported, tmp_path, capsys):
    from jepa_envs.cli import main

    root = copy(exported[0], tmp_path)
    frames = exported[1]["frames"]
    _add_feature(root, "observation.effort", np.ones((frames, 3), np.float32),
                 {"dtype": "float32", "shape": [3], "names": None})
    summary = import_lerobot(root, tmp_path / "a.hdf5", "PushT")
    assert summary["unmapped"] == {"observation.effort": "float32 [3]"}
    assert main(["lerobot", "import", str(root), str(tmp_path / "b.hdf5"), "--task", "PushT"]) == 0
    err = capsys.readouterr().err
    assert "'observation.effort' (float32 [3]) was not imported" in err and "--map observation.effort=" in err


def test_every_mismatch_is_reported_at_once(exported, tmp_path):
    message = refused(exported[0], tmp_path, "does not fit task Square", task="Square")
    assert "(5 problems)" in message
    for part in ("records at 10 fps, task Square acts at 20 Hz", "no feature 'observation.images.agentview'",
                 "no feature 'observation.images.robot0_eye_in_hand'", "'observation.state' has shape [2]",
                 "'action' has shape [2]; task Square acts with 10-D"):
        assert part in message, part


def test_fps_must_be_the_datasets_own_and_its_timestamps_follow_it(exported, tmp_path):
    refused(exported[0], tmp_path, r"--fps 20 is not the dataset's rate \(10 fps in info.json\)", fps=20)
    root = copy(exported[0], tmp_path)
    table = pq.read_table(root / "data/chunk-000/file-000.parquet")
    timestamps = (np.asarray(table.column("frame_index")) / 20).astype(np.float32)   # recorded at 20 fps
    table = table.set_column(table.schema.get_field_index("timestamp"), "timestamp", pa.array(timestamps))
    pq.write_table(table, root / "data/chunk-000/file-000.parquet")
    refused(root, tmp_path, r"episode 0's timestamps do not follow info.json's 10 fps .* step 0.0500 s = 20 fps")


def test_import_refuses_an_existing_file_unless_told(exported, tmp_path):
    out = tmp_path / "mine.hdf5"
    out.write_text("keep me")
    with pytest.raises(LeRobotError, match="mine.hdf5 exists; pass another path, or --overwrite"):
        import_lerobot(exported[0], out, "PushT")
    assert out.read_text() == "keep me"
    import_lerobot(exported[0], out, "PushT", overwrite=True)
    assert len(load_dataset(out, task="PushT", cache_dir=False).episode_ends) == 4


def test_a_missing_path_is_named_as_missing(tmp_path):
    with pytest.raises(LeRobotError, match=r"nope does not exist; pass the root folder"):
        import_lerobot(tmp_path / "nope", tmp_path / "out.hdf5", "PushT")


def test_import_finds_the_task_the_dataset_names(exported, tmp_path, capsys):
    """README's `jepa-envs lerobot import DIR OUT.hdf5` works on our exports without --task (its episodes on a
    bar; the export's too)."""
    from jepa_envs.cli import main

    assert import_lerobot(exported[0], tmp_path / "a.hdf5")["task"] == "PushT"
    assert main(["lerobot", "import", str(exported[0]), str(tmp_path / "b.hdf5")]) == 0
    episodes = exported[1]["episodes"]
    assert "lerobot import: 100%" in capsys.readouterr().err
    assert main(["lerobot", "export", str(tmp_path / "b.hdf5"), str(tmp_path / "again")]) == 0
    assert f"{episodes}/{episodes}" in capsys.readouterr().err
    assert main(["lerobot", "import", str(exported[0]), str(tmp_path / "c.hdf5"), "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
    root = copy(exported[0], tmp_path)
    edit_info(root, robot_type="koch")
    refused(root, tmp_path, r"names no task of ours \(robot_type 'koch'\); pass --task", task=None)


def test_train_on_a_root_at_another_rate_advises_what_train_can_do(pusht_demo_file, tmp_path, monkeypatch):
    """`jepa-policy train --dataset ROOT` has no --fps: the fix it names is an import that accepts the rate, and
    following it gives a file train reads."""
    from jepa_envs.cli import main
    from jepa_envs.datasets.lerobot import export_lerobot

    monkeypatch.setenv("JEPA_DATA_CACHE", str(tmp_path / "cache"))
    root = tmp_path / "at20"
    export_lerobot(pusht_demo_file, root, fps=20)
    with pytest.raises(LeRobotError) as err:
        resolve_dataset(root, "PushT")
    message = str(err.value)
    assert "pass --fps" not in message and "train with --dataset OUT.hdf5" in message
    command = message.split("(jepa-envs ", 1)[1].split(")", 1)[0].replace("OUT.hdf5", str(tmp_path / "out.hdf5"))
    assert command.endswith("--fps 20")
    assert main(command.split()) == 0
    assert resolve_dataset(tmp_path / "out.hdf5", "PushT") == tmp_path / "out.hdf5"
