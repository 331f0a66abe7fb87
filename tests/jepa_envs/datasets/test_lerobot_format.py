"""LeRobotDataset v3.0 in and out: the layout LeRobot reads, a round trip that gives our arrays back, and every
bad dataset refused in one line with nothing written. (LeRobot's own code reading and writing these files is
checked by `make interop`, in a venv of its own.)"""
from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest

from jepa_envs.datasets.hdf5 import demo_names, load_dataset
from jepa_envs.datasets.lerobot_format import (CODEBASE_VERSION, KeyMap, LeRobotError, export_lerobot, import_lerobot,
                                      open_lerobot, resolve_dataset)
from jepa_envs.tasks.spec import get_task_spec


@pytest.fixture(scope="module")
def exported(pusht_demo_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot") / "pusht"
    summary = export_lerobot(pusht_demo_file, out)
    return out, summary


def _arrays(path) -> list[dict]:
    with h5py.File(path) as f:
        return [{key: f["data"][n][key][()] for key in ("actions", "states", "rewards", "dones")}
                | {f"obs/{k}": f["data"][n]["obs"][k][()] for k in f["data"][n]["obs"]}
                | {"task": f["data"][n].attrs.get("task")} for n in demo_names(f["data"])]


def test_export_writes_lerobots_v3_layout(exported, pusht_demo_file):
    root, summary = exported
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == CODEBASE_VERSION == "v3.0" and info["fps"] == 10
    assert info["total_episodes"] == summary["episodes"] == 4 and info["splits"] == {"train": "0:4"}
    feats = info["features"]
    assert feats["observation.images.top"]["dtype"] == "video" and feats["observation.images.top"]["shape"] == [84, 84, 3]
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


def test_round_trip_gives_the_arrays_back(exported, pusht_demo_file, tmp_path):
    root, _ = exported
    back = tmp_path / "back.hdf5"
    import_lerobot(root, back, "PushT")
    ours, theirs = _arrays(pusht_demo_file), _arrays(back)
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs):
        for key in ("actions", "states", "rewards", "dones", "obs/agent_pos", "obs/top_image"):
            assert np.array_equal(a[key], b[key]), key    # lossless video: frames bit-identical too
        assert b["task"] == "PushT"   # the task string every exported episode got
    demos = load_dataset(back, task="PushT", cache_dir=False)
    assert demos.episode_ends.tolist() == load_dataset(pusht_demo_file, cache_dir=False).episode_ends.tolist()


def test_av1_round_trip_is_within_the_codecs_loss(pusht_demo_file, tmp_path):
    export_lerobot(pusht_demo_file, tmp_path / "av1", codec="av1")
    import_lerobot(tmp_path / "av1", tmp_path / "back.hdf5", "PushT")
    for a, b in zip(_arrays(pusht_demo_file), _arrays(tmp_path / "back.hdf5")):
        assert np.array_equal(a["actions"], b["actions"])
        err = np.abs(a["obs/top_image"].astype(float) - b["obs/top_image"])
        assert err.mean() < 3.0 and 10 * np.log10(255 ** 2 / (err ** 2).mean()) > 33   # 4:2:0, CRF 30


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


# ----------------------------------------------------------------------------- bad datasets: one line, nothing written


def _copy(root, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(root, dst)
    return dst


def _edit_info(root, **changes):
    info = json.loads((root / "meta/info.json").read_text())
    info.update(changes)
    (root / "meta/info.json").write_text(json.dumps(info))


def _refused(root, tmp_path, match, task="PushT", **kwargs):
    out = tmp_path / "out.hdf5"
    with pytest.raises(LeRobotError, match=match) as err:
        import_lerobot(root, out, task, **kwargs)
    assert "\n" not in str(err.value)
    assert not out.exists() and not list(tmp_path.glob("out.hdf5.*")), "nothing half-written"


def test_another_codebase_version_is_refused(exported, tmp_path):
    root = _copy(exported[0], tmp_path)
    _edit_info(root, codebase_version="v2.1")
    _refused(root, tmp_path, "LeRobotDataset v2.1.*convert_dataset_v21_to_v30")


def test_truncated_parquet_is_refused(exported, tmp_path):
    root = _copy(exported[0], tmp_path)
    data = root / "data/chunk-000/file-000.parquet"
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    _refused(root, tmp_path, "data/chunk-000/file-000.parquet is not a readable parquet file")


def test_video_shorter_than_its_episode_is_refused(exported, pusht_demo_file, tmp_path):
    """A video re-encoded without the last episode's final frames."""
    from jepa_envs.datasets.lerobot_format import VideoWriter

    root = _copy(exported[0], tmp_path)
    with h5py.File(pusht_demo_file) as f:
        frames = np.concatenate([f["data"][n]["obs/top_image"][()] for n in demo_names(f["data"])])
    video = root / "videos/observation.images.top/chunk-000/file-000.mp4"
    video.unlink()
    writer = VideoWriter(root, "observation.images.top", 10, "lossless", 84, 84)
    writer.add_episode(frames[:-5], 0)
    writer.close()
    _refused(root, tmp_path, "holds .* frames of episode 3 .* the video is shorter than its episode")


def test_missing_video_is_refused(exported, tmp_path):
    root = _copy(exported[0], tmp_path)
    (root / "videos/observation.images.top/chunk-000/file-000.mp4").unlink()
    _refused(root, tmp_path, "file-000.mp4 is missing")


def test_shape_disagreeing_with_info_is_refused(exported, tmp_path):
    root = _copy(exported[0], tmp_path)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["observation.images.top"]["shape"] = [96, 96, 3]
    (root / "meta/info.json").write_text(json.dumps(info))
    _refused(root, tmp_path, r"episode 0's frames are \[84, 84, 3\], info.json says \[96, 96, 3\]")


def test_missing_feature_and_fps_and_map_are_named(exported, tmp_path):
    root = exported[0]
    _refused(root, tmp_path, "acts at 20 Hz; pass --fps 10", task="Square")
    _refused(root, tmp_path, "no feature 'observation.images.agentview'", task="Square", fps=10)
    _refused(root, tmp_path, "'actions'.*not a key|no feature 'act'", key_map=["act=action"])
    _refused(root, tmp_path, "has shape \\[5\\]; task PushT's", key_map=["observation.environment_state=agent_pos"])


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


def test_a_dataset_with_embedded_png_images_imports(exported, tmp_path):
    """LeRobot's `image` features (PNG bytes in the data parquet) read as well as videos."""
    import io

    import pyarrow as pa
    from PIL import Image

    root = _copy(exported[0], tmp_path)
    ds = open_lerobot(root)
    back = tmp_path / "video.hdf5"
    import_lerobot(root, back, "PushT")
    frames = np.concatenate([ep["obs/top_image"] for ep in _arrays(back)])
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
    assert np.array_equal(np.concatenate([ep["obs/top_image"] for ep in _arrays(tmp_path / "png.hdf5")]), frames)
    assert ds.fps == 10


def test_twenty_av1_exports_in_a_row_finish_with_every_frame_in_order(pusht_demo_file, tmp_path):
    """SVT-AV1 4.1 with more than one thread per stage (its default on >1 core) sometimes hands out a frame's
    packet 74 frames early (the picture slot it reuses), which the muxer refuses (EINVAL in close()), or stalls
    for good in svt_av1_enc_get_packet: 1-3 exports in 60 failed so under load before the encoder ran one thread."""
    import av

    for i in range(20):
        out = tmp_path / f"av1_{i}"
        summary = export_lerobot(pusht_demo_file, out, codec="av1", encoder_timeout_s=30)
        with av.open(str(out / "videos/observation.images.top/chunk-000/file-000.mp4")) as container:
            stream = container.streams.video[0]
            frames = [round(p.pts * stream.time_base * 10) for p in container.demux(stream) if p.pts is not None]
        assert frames == list(range(summary["frames"])), f"export {i}: packets out of order"
        shutil.rmtree(out)


def test_a_stalled_encoder_stops_the_export_with_its_episode(pusht_demo_file, tmp_path, monkeypatch):
    """Fault injection: the encoder stops taking frames in episode 2 (as SVT-AV1 did inside
    svt_av1_enc_get_packet). The export must end with the episode and the fix, not wait for good."""
    import threading
    import time

    from jepa_envs.datasets.lerobot_format import VideoWriter

    release = threading.Event()
    encode = VideoWriter._encode

    def stalling(self, frames):
        if self.episode == 2:
            release.wait()
        encode(self, frames)

    monkeypatch.setattr(VideoWriter, "_encode", stalling)
    t0 = time.perf_counter()
    try:
        with pytest.raises(LeRobotError, match=r"made no progress for 0.5 s while encoding episode 2.*"
                                               r"--codec lossless or h264") as err:
            export_lerobot(pusht_demo_file, tmp_path / "out", codec="av1", encoder_timeout_s=0.5)
    finally:
        release.set()
    assert time.perf_counter() - t0 < 10 and "\n" not in str(err.value)
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*")), "nothing half-written"
