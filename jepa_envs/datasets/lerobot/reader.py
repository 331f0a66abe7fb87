"""Reading a LeRobotDataset v3.0 root: its metadata checked on open, then our episode dicts one at a time
(data rows by record batch, video frames by sequential decode, embedded PNG images)."""
from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import pyarrow.parquet as pq

from jepa_envs.datasets.lerobot.format import (CODEBASE_VERSION, DONE, INFO_PATH, REWARD, SUCCESS, TASKS_PATH,
                                               TOLERANCE_S, KeyMap, LeRobotError, short_error)
from jepa_envs.datasets.lerobot.video import VideoReader
from jepa_envs.tasks.spec import TaskSpec


@dataclass
class LeRobotDataset:
    """A LeRobot v3.0 root as this module reads it: info, tasks, episodes (all validated on open)."""

    root: Path
    info: dict
    tasks: list[str]
    episodes: list[dict]
    features: dict = field(default_factory=dict)

    @property
    def fps(self) -> int:
        return int(self.info["fps"])


def is_lerobot_root(path: str | Path) -> bool:
    """Whether ``path`` is a LeRobot dataset's root folder (it holds meta/info.json)."""
    return (Path(path) / INFO_PATH).is_file()


def open_lerobot(root: str | Path) -> LeRobotDataset:
    """Read and check a LeRobot dataset's metadata (codebase version, files, totals)."""
    root = Path(root)
    info_path = root / INFO_PATH
    if not root.exists():
        raise LeRobotError(f"{root} does not exist; pass the root folder of a LeRobotDataset v3.0 (the one holding "
                           f"{INFO_PATH})")
    if not info_path.is_file():
        raise LeRobotError(f"{root} has no {INFO_PATH}; pass the root folder of a LeRobotDataset v3.0")
    try:
        info = json.loads(info_path.read_text())
    except ValueError as exc:
        raise LeRobotError(f"{info_path} is not valid JSON ({exc}); re-download the dataset's meta folder") from None
    version = str(info.get("codebase_version", "<none>"))
    if version != CODEBASE_VERSION:
        fix = ("convert it with LeRobot's `python -m lerobot.datasets.v30.convert_dataset_v21_to_v30`"
               if version.startswith("v2") else "use a v3.0 dataset")
        raise LeRobotError(f"{root} is LeRobotDataset {version}, this reader reads {CODEBASE_VERSION}; {fix}")
    for needed in ("fps", "features", "total_episodes", "total_frames", "data_path"):
        if needed not in info:
            raise LeRobotError(f"{info_path} has no {needed!r}; it is not a LeRobot v3.0 info.json")
    try:
        tasks_table = pq.read_table(str(root / TASKS_PATH))
    except FileNotFoundError:
        raise LeRobotError(f"{root / TASKS_PATH} is missing; download the dataset's meta folder whole") from None
    except Exception as exc:
        raise LeRobotError(f"{TASKS_PATH} is not a readable parquet file ({short_error(exc)}); "
                           "re-download it") from None
    tasks = _task_strings(tasks_table)
    episodes = []
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise LeRobotError(f"{root}/meta/episodes has no chunk-*/file-*.parquet; download the meta folder whole")
    for path in files:
        try:
            episodes += pq.read_table(str(path)).to_pylist()
        except Exception as exc:
            raise LeRobotError(f"{path.relative_to(root)} is not a readable parquet file ({short_error(exc)}); "
                               "re-download it") from None
    episodes.sort(key=lambda ep: ep["episode_index"])
    if len(episodes) != info["total_episodes"]:
        raise LeRobotError(f"info.json says {info['total_episodes']} episodes, meta/episodes lists {len(episodes)}; "
                           "re-download the meta folder")
    return LeRobotDataset(root, info, tasks, episodes, info["features"])


def _task_strings(table) -> list[str]:
    names = table.column_names
    rows = table.to_pylist()
    text_col = next((c for c in ("task", "__index_level_0__") if c in names), None)
    if text_col is None or "task_index" not in names:
        raise LeRobotError(f"{TASKS_PATH} has columns {names}; it needs the task strings and task_index")
    out = [""] * len(rows)
    for row in rows:
        out[int(row["task_index"])] = row[text_col]
    return out


def iter_episodes(ds: LeRobotDataset, spec: TaskSpec, km: KeyMap) -> Iterator[dict]:
    """Our episode dicts (``obs``, ``actions``, ``states``, ``rewards``, ``dones``, ``attrs``), one at a time."""
    rows = _RowStream(ds)
    videos = {key: VideoReader(ds.root, key) for key, ft in ds.features.items()
              if key in km.images and ft["dtype"] == "video"}
    state_key, state_keys = km.state
    dims = dict(spec.lowdim)
    for ep in ds.episodes:
        e, n = int(ep["episode_index"]), int(ep["length"])
        data = rows.take(e, n)
        _check_timestamps(data, ds.fps, e)
        obs = {}
        offset = 0
        state = np.asarray(data[state_key], np.float32).reshape(n, -1)
        for key in state_keys:
            obs[key] = state[:, offset:offset + dims[key]]
            offset += dims[key]
        for key, target in km.images.items():
            if key in videos:
                frames = videos[key].episode(ep[f"videos/{key}/chunk_index"], ep[f"videos/{key}/file_index"],
                                             float(ep[f"videos/{key}/from_timestamp"]),
                                             float(ep[f"videos/{key}/to_timestamp"]), n, e)
            else:
                frames = np.stack([_png(cell, key, e) for cell in data[key]])
            expected = tuple(ds.features[key]["shape"])
            if frames.shape[1:] != expected:
                raise LeRobotError(f"feature {key!r}: episode {e}'s frames are {list(frames.shape[1:])}, info.json "
                                   f"says {list(expected)}; the files disagree with their metadata")
            obs[target] = frames
        episode = {"obs": obs, "actions": np.asarray(data[km.action], np.float32).reshape(n, -1),
                   "attrs": {"task": ds.tasks[int(data["task_index"][0])], "lerobot_episode_index": e}}
        if km.env_state and km.env_state in ds.features:
            episode["states"] = np.asarray(data[km.env_state]).reshape(n, -1)
        if REWARD in ds.features:
            episode["rewards"] = np.asarray(data[REWARD], np.float32).reshape(n)
        if DONE in ds.features:
            episode["dones"] = np.asarray(data[DONE]).astype(np.uint8).reshape(n)
        if SUCCESS in ds.features:
            episode["attrs"]["success"] = bool(np.asarray(data[SUCCESS]).reshape(n)[-1])
        yield episode


def _check_timestamps(data: dict, fps: int, episode: int) -> None:
    """The rows' timestamps step 1/fps from the episode's first (LeRobot's own loader checks the same, within
    the same tolerance): a dataset whose info.json names another rate than its data cannot be timed."""
    if "timestamp" not in data:
        raise LeRobotError(f"the data files have no 'timestamp' column (episode {episode}); LeRobot writes one per "
                           "row: re-download the data folder")
    ts = np.asarray(data["timestamp"], np.float64).reshape(-1)
    off = np.abs(ts - ts[0] - np.arange(len(ts)) / fps)
    if len(ts) and off.max() > TOLERANCE_S:
        row = int(np.argmax(off > TOLERANCE_S))
        step = float(np.median(np.diff(ts))) if len(ts) > 1 else float("nan")
        raise LeRobotError(f"episode {episode}'s timestamps do not follow info.json's {fps} fps (row {row} is at "
                           f"{ts[row]:.4f} s, {fps} fps puts it at {ts[0] + row / fps:.4f} s; its rows step "
                           f"{step:.4f} s = {1 / step if step > 0 else float('nan'):.3g} fps); the data and its "
                           "fps disagree: fix info.json's fps or re-record the dataset")


def _png(cell, key: str, episode: int) -> np.ndarray:
    from PIL import Image

    raw = cell.get("bytes") if isinstance(cell, dict) else None
    if not raw:
        raise LeRobotError(f"feature {key!r} of episode {episode} holds no embedded image bytes; LeRobot embeds "
                           "them when it saves an episode (an image path alone cannot be read here)")
    return np.asarray(Image.open(io.BytesIO(raw)).convert("RGB"))


class _RowStream:
    """The data files' rows in index order, taken one episode at a time (record batches, never a whole file)."""

    def __init__(self, ds: LeRobotDataset):
        self.ds = ds
        self.files = sorted((ds.root / "data").glob("chunk-*/file-*.parquet"))
        if not self.files:
            raise LeRobotError(f"{ds.root}/data has no chunk-*/file-*.parquet; download the dataset's data folder")
        self.batches = self._batches()
        self.buffer: dict[str, list] = {}
        self.columns: list[str] = []

    def _batches(self):
        for path in self.files:
            rel = path.relative_to(self.ds.root)
            try:
                pfile = pq.ParquetFile(str(path))
                yield from pfile.iter_batches(batch_size=4096)
            except Exception as exc:
                raise LeRobotError(f"{rel} is not a readable parquet file ({short_error(exc)}); "
                                   "re-download it") from None

    def take(self, episode: int, n: int) -> dict[str, list]:
        while not self.buffer or len(self.buffer["episode_index"]) < n:
            batch = next(self.batches, None)
            if batch is None:
                have = len(self.buffer.get("episode_index", []))
                raise LeRobotError(f"the data files end after {have} of episode {episode}'s {n} rows; a data file "
                                   "is truncated or missing: re-download the data folder")
            part = batch.to_pydict()
            for key, values in part.items():
                self.buffer.setdefault(key, []).extend(values)
        out = {key: values[:n] for key, values in self.buffer.items()}
        self.buffer = {key: values[n:] for key, values in self.buffer.items()}
        if set(out["episode_index"]) != {episode} or out["frame_index"] != list(range(n)):
            raise LeRobotError(f"rows of episode {episode} are not the next {n} rows of the data files (found "
                               f"episodes {sorted(set(out['episode_index']))[:4]}); the episodes metadata and the "
                               "data disagree: re-download the dataset")
        return out
