"""Export: a robomimic-layout demos (or rollouts) HDF5 file -> a LeRobotDataset v3.0 folder, one episode at a
time, into a temporary folder renamed into place at the end."""
from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from jepa_envs.datasets.hdf5 import demo_names, open_hdf5, resolve_task
from jepa_envs.datasets.lerobot.format import (ACTION, CHUNKS_SIZE, CODEBASE_VERSION, CODECS, DATA_FILE_MB, DATA_PATH,
                                               DEFAULT_FEATURES, DONE, ENCODER_TIMEOUT_S, ENV_STATE, EPISODES_PATH,
                                               INFO_PATH, REWARD, ROBOT_TYPE_PREFIX, STATE, STATS_PATH, SUCCESS,
                                               TASKS_PATH, VIDEO_FILE_MB, VIDEO_PATH, LeRobotError, image_features,
                                               instruction_for, jsonable, next_file)
from jepa_envs.datasets.lerobot.stats import RunningStats, episode_stats
from jepa_envs.datasets.lerobot.video import VideoWriter
from jepa_envs.tasks.spec import TaskSpec


def export_lerobot(src: str | Path, out_dir: str | Path, task: str | None = None, fps: int | None = None,
                   codec: str = "lossless", instruction: str | None = None, robot_type: str | None = None,
                   encoder_timeout_s: float = ENCODER_TIMEOUT_S, progress: bool = False) -> dict:
    """Write a robomimic-layout demos (or rollouts) file as a LeRobotDataset v3.0 folder; returns a summary
    (``progress``: a bar of the episodes on stderr).

    ``fps`` defaults to the rate the file was recorded at (a LeRobot import keeps it), else the task's control
    rate; another rate than the recorded one is refused (it would re-time the frames, not resample them). An
    encoder that makes no progress for ``encoder_timeout_s`` stops the export with the episode it was on."""
    if codec not in CODECS:
        raise LeRobotError(f"codec {codec!r} is not one of {sorted(CODECS)}")
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        what = "is not empty" if out.is_dir() else "is not a folder"
        raise LeRobotError(f"{out} exists and {what}; pass a new folder (nothing was written)")
    if not out.parent.is_dir():
        raise LeRobotError(f"{out.parent} does not exist; create it first, the export goes into a new folder inside "
                           "it (nothing was written)")
    with open_hdf5(src) as f:
        if "data" not in f or not demo_names(f["data"]):
            raise LeRobotError(f"{src} holds no data/demo_N episodes; write demos with `jepa-envs make-demos`")
        env_args = json.loads(f["data"].attrs.get("env_args", "{}"))
        spec = resolve_task(task, env_args, src)
        fps = _export_fps(fps, env_args, spec, src)
        names = demo_names(f["data"])
        first = f["data"][names[0]]
        features = _export_features(spec, first, src)
        # beside the target: the final rename stays on one file system, and a bad target fails before any work
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        try:
            summary = _write_export(f, names, spec, features, tmp, fps, codec, instruction, robot_type,
                                    encoder_timeout_s, progress)
            if out.exists():
                out.rmdir()
            tmp.rename(out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return {**summary, "out": str(out)}


def _export_fps(fps: int | None, env_args: dict, spec: TaskSpec, src) -> int:
    recorded = (env_args.get("lerobot") or {}).get("fps")
    if fps is not None and fps <= 0:
        raise LeRobotError(f"--fps must be a positive number of frames per second, got {fps}")
    if recorded is not None and fps is not None and fps != recorded:
        raise LeRobotError(f"{src} was recorded at {recorded} fps (imported from {env_args['lerobot'].get('root')}); "
                           f"--fps {fps} would re-time its frames, not resample them: leave --fps out")
    return int(fps or recorded or round(spec.control_hz))


def _export_features(spec: TaskSpec, demo, src) -> dict:
    obs = demo["obs"]
    features: dict = {}
    for feature, key in image_features(spec).items():
        if key not in obs:
            raise LeRobotError(f"{src}: data/demo_0/obs has no {key!r} (task {spec.name} needs it); for a file "
                               "with states only, render it first: jepa-envs render-dataset")
        _, h, w, c = obs[key].shape
        features[feature] = {"dtype": "video", "shape": [h, w, c], "names": ["height", "width", "channels"]}
    names = []
    for key, dim in spec.lowdim:
        if key not in obs:
            raise LeRobotError(f"{src}: data/demo_0/obs has no {key!r} (task {spec.name} needs it)")
        names += [f"{key}[{i}]" for i in range(dim)]
    features[STATE] = {"dtype": "float32", "shape": [len(names)], "names": names}
    if "states" in demo:
        features[ENV_STATE] = {"dtype": "float32" if demo["states"].dtype == np.float32 else "float64",
                               "shape": [int(demo["states"].shape[1])], "names": None}
    features[ACTION] = {"dtype": "float32", "shape": [int(demo["actions"].shape[1])], "names": None}
    if "rewards" in demo:
        features[REWARD] = {"dtype": "float32", "shape": [1], "names": None}
    if "dones" in demo:
        features[DONE] = {"dtype": "bool", "shape": [1], "names": None}
    if "success" in demo.attrs:
        features[SUCCESS] = {"dtype": "bool", "shape": [1], "names": None}
    return {**features, **DEFAULT_FEATURES}


def _arrow_type(ft: dict):
    dtype = {"float32": pa.float32(), "float64": pa.float64(), "int64": pa.int64(), "bool": pa.bool_()}[ft["dtype"]]
    return dtype if ft["shape"] == [1] else pa.list_(dtype, ft["shape"][0])   # datasets' Sequence(length=D)


def _write_export(f, names, spec, features, root: Path, fps: int, codec: str, instruction, robot_type,
                  encoder_timeout_s: float, progress: bool = False) -> dict:
    vectors = {k: ft for k, ft in features.items() if ft["dtype"] != "video"}
    schema = pa.schema([(k, _arrow_type(ft)) for k, ft in vectors.items()])
    videos = {k: VideoWriter(root, k, fps, codec, ft["shape"][0], ft["shape"][1], encoder_timeout_s)
              for k, ft in features.items() if ft["dtype"] == "video"}
    stats = {k: RunningStats(image=ft["dtype"] == "video") for k, ft in features.items()}
    tasks: dict[str, int] = {}
    episodes: list[dict] = []
    data_chunk = data_file = 0
    writer = None
    index = 0
    try:
        for e, name in enumerate(tqdm(names, desc="lerobot export", unit="episode", disable=not progress)):
            demo = f["data"][name]
            obs = demo["obs"]
            n = int(demo["actions"].shape[0])
            text = demo.attrs.get("task", instruction or instruction_for(spec))
            text = text.decode() if isinstance(text, bytes) else str(text)
            task_index = tasks.setdefault(text, len(tasks))
            columns = {
                STATE: np.concatenate([np.asarray(obs[k][()], np.float32).reshape(n, -1) for k in spec.lowdim_keys], 1),
                ACTION: np.asarray(demo["actions"][()], np.float32)}
            if ENV_STATE in features:
                columns[ENV_STATE] = np.asarray(demo["states"][()], features[ENV_STATE]["dtype"])
            if REWARD in features:
                columns[REWARD] = np.asarray(demo["rewards"][()], np.float32).reshape(n)
            if DONE in features:
                columns[DONE] = np.asarray(demo["dones"][()]).astype(bool).reshape(n)
            if SUCCESS in features:   # a rollout's outcome: true on its last frame only
                columns[SUCCESS] = np.zeros(n, bool)
                columns[SUCCESS][-1] = bool(demo.attrs["success"])
            for key, ft in features.items():
                if ft["dtype"] not in ("video",) and key not in DEFAULT_FEATURES and len(columns[key]) != n:
                    raise LeRobotError(f"data/{name}: {key} has {len(columns[key])} rows but actions have {n}")
            columns["timestamp"] = (np.arange(n) / fps).astype(np.float32)
            columns["frame_index"] = np.arange(n, dtype=np.int64)
            columns["episode_index"] = np.full(n, e, np.int64)
            columns["index"] = np.arange(index, index + n, dtype=np.int64)
            columns["task_index"] = np.full(n, task_index, np.int64)
            if writer is not None and writer.path.stat().st_size / 2**20 >= DATA_FILE_MB:
                writer.close()
                writer = None
                data_chunk, data_file = next_file(data_chunk, data_file)
            if writer is None:
                path = root / DATA_PATH.format(chunk_index=data_chunk, file_index=data_file)
                path.parent.mkdir(parents=True, exist_ok=True)
                writer = pq.ParquetWriter(str(path), schema, compression="snappy")
                writer.path = path
            arrays = []
            for key in vectors:
                col = columns[key]
                arrays.append(pa.array(col) if col.ndim == 1 else
                              pa.FixedSizeListArray.from_arrays(pa.array(col.reshape(-1)), col.shape[1]))
            writer.write_table(pa.Table.from_arrays(arrays, schema=schema))
            row = {"episode_index": e, "tasks": [text], "length": n, "data/chunk_index": data_chunk,
                   "data/file_index": data_file, "dataset_from_index": index, "dataset_to_index": index + n}
            for key, video in videos.items():
                frames = obs[image_features(spec)[key]][()]
                if frames.shape[0] != n or frames.dtype != np.uint8:
                    raise LeRobotError(f"data/{name}/obs/{image_features(spec)[key]} has shape {frames.shape} "
                                       f"{frames.dtype}; it needs {n} uint8 frames")
                row.update(video.add_episode(frames, e))
                row.update(episode_stats(key, stats[key].add(frames)))
            for key in vectors:   # LeRobot keeps statistics of every feature, the frame counters included
                row.update(episode_stats(key, stats[key].add(columns[key].reshape(n, -1))))
            row["meta/episodes/chunk_index"], row["meta/episodes/file_index"] = 0, 0
            episodes.append(row)
            index += n
        for video in videos.values():
            video.close()
    finally:
        if writer is not None:
            writer.close()
        for video in videos.values():
            video.discard()
    for key, video in videos.items():
        features[key]["info"] = video.info()
    _write_meta(root, features, episodes, tasks, stats, fps, robot_type or f"{ROBOT_TYPE_PREFIX}{spec.name}")
    return {"episodes": len(episodes), "frames": index, "tasks": list(tasks), "fps": fps, "codec": codec,
            "task": spec.name}



def _write_meta(root: Path, features, episodes, tasks, stats, fps, robot_type) -> None:
    path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(episodes), str(path), compression="snappy")
    _write_tasks(root, tasks)
    (root / STATS_PATH).write_text(json.dumps(jsonable({k: s.result() for k, s in stats.items()}), indent=4))
    total = sum(ep["length"] for ep in episodes)
    info = {"codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": len(episodes),
            "total_frames": total, "total_tasks": len(tasks), "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB, "fps": fps,
            "splits": {"train": f"0:{len(episodes)}"}, "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if any(ft["dtype"] == "video" for ft in features.values()) else None,
            "features": features}
    (root / INFO_PATH).write_text(json.dumps(info, indent=4))


def _write_tasks(root: Path, tasks: dict[str, int]) -> None:
    """meta/tasks.parquet as pandas writes ``DataFrame({"task_index": ...}, index=tasks)``: the task strings are
    the frame's index (LeRobot reads it with ``pd.read_parquet`` and looks tasks up by that index)."""
    texts = sorted(tasks, key=tasks.get)
    pandas_meta = {"index_columns": ["__index_level_0__"], "column_indexes": [{
        "name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
        "metadata": {"encoding": "UTF-8"}}], "columns": [
        {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
         "metadata": None},
        {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object",
         "metadata": None}], "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0"}
    table = pa.table({"task_index": pa.array([tasks[t] for t in texts], pa.int64()),
                      "__index_level_0__": pa.array(texts, pa.string())})
    table = table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})
    pq.write_table(table, str(root / TASKS_PATH))
