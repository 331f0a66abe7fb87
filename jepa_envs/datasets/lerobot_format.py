"""LeRobotDataset v3.0 in and out: our robomimic-layout demos to LeRobot's layout, and LeRobot datasets back.

The layout is LeRobot's own (huggingface/lerobot, ``src/lerobot/datasets/``: ``utils.py`` for the paths and
``DEFAULT_FEATURES``, ``lerobot_dataset.py`` for what ``save_episode`` writes), written with pyarrow and PyAV:

    meta/info.json                              codebase_version "v3.0", fps, features (dtype/shape/names), totals
    meta/tasks.parquet                          one row per task string (the pandas index), column task_index
    meta/stats.json                             per feature: min, max, mean, std, count, q01 q10 q50 q90 q99
    meta/episodes/chunk-000/file-000.parquet    one row per episode: length, tasks, where its rows and frames lie
    data/chunk-000/file-000.parquet             one row per frame: the vector features, timestamp, frame_index,
                                                episode_index, index, task_index
    videos/<key>/chunk-000/file-000.mp4         one video per camera, episodes one after the other

Our keys map to LeRobot's conventions: camera ``<c>_image`` -> ``observation.images.<c>`` (video), the task's
low-dim keys concatenated in spec order -> ``observation.state`` (names ``key[i]``), ``states`` (simulator state)
-> ``observation.environment_state``, ``actions`` -> ``action``, ``rewards`` -> ``next.reward``, ``dones`` ->
``next.done``, and the episode's instruction -> its task string. ``KeyMap`` turns another dataset's names into
the task spec's keys (``--map observation.images.front=agentview_image``).

Videos: ``lossless`` (default) is H.264 in RGB (``libx264rgb``, CRF 0): frames come back bit-identical, and
LeRobot decodes it (any FFmpeg codec is allowed in its ``info.json``); ``av1`` is LeRobot's own default
(``libsvtav1``, yuv420p, CRF 30, GOP 2) and loses detail to 4:2:0 chroma and quantisation.

Both directions stream one episode at a time: memory holds one episode's frames, never the whole dataset. A
dataset that cannot be used (another codebase version, a missing or truncated file, a video shorter than its
episode, a feature whose shape disagrees with info.json, a key the task needs that the map does not give) is
refused with one line naming it and the fix, and nothing is written: output goes to a temporary folder or file
renamed into place at the end.
"""
from __future__ import annotations

import hashlib
import io
import json
import shutil
import tempfile
import threading
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Iterator

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from jepa_envs.datasets.hdf5 import DemoWriter, default_cache_dir, demo_names, open_hdf5, resolve_task
from jepa_envs.errors import first_line
from jepa_envs.tasks.spec import TaskSpec, get_task_spec

CODEBASE_VERSION = "v3.0"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
CHUNKS_SIZE = 1000             # files per chunk folder
DATA_FILE_MB = 100             # a data file is closed past this size
VIDEO_FILE_MB = 200            # a video file is closed past this size
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
DEFAULT_FEATURES = {           # LeRobot's DEFAULT_FEATURES: every frame row has them
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
IMAGES = "observation.images."
STATE = "observation.state"
ENV_STATE = "observation.environment_state"
ACTION = "action"
REWARD = "next.reward"
DONE = "next.done"
SUCCESS = "next.success"
CODECS = {   # name: (FFmpeg encoder, pixel format, options)
    "lossless": ("libx264rgb", "rgb24", {"crf": "0", "preset": "veryfast", "g": "2", "bf": "0"}),
    # lp=1: one thread per SVT-AV1 stage. With more (its default: one per core), SVT-AV1 4.1 now and then hands
    # a frame's packet out 74 frames early (the picture slot it reuses), which the muxer refuses, or stalls for
    # good in svt_av1_enc_get_packet: 8 in 10 runs of 20 exports failed so, 0 in 250 exports with lp=1
    "av1": ("libsvtav1", "yuv420p", {"crf": "30", "g": "2", "svtav1-params": "lp=1"}),
    "h264": ("libx264", "yuv420p", {"crf": "18", "preset": "veryfast", "g": "2", "bf": "0"}),
}
TOLERANCE_S = 1e-4             # a frame belongs to an episode when its time lies in [from, to) within this
ENCODER_TIMEOUT_S = 60.0       # an encoder that takes no frame and hands back no packet for this long has stalled


class LeRobotError(ValueError):
    """A LeRobot dataset (or a demos file to export) that cannot be used; the message names it and the fix."""


# ----------------------------------------------------------------------------- key map


@dataclass
class KeyMap:
    """Which LeRobot feature fills which of the task spec's keys."""

    images: dict[str, str]                 # LeRobot image/video feature -> spec image key
    state: tuple[str, tuple[str, ...]]     # (LeRobot vector feature, spec low-dim keys it concatenates in order)
    action: str = ACTION
    env_state: str | None = ENV_STATE      # -> ``states`` (simulator state) when the dataset has it

    @classmethod
    def default(cls, spec: TaskSpec) -> "KeyMap":
        return cls({f"{IMAGES}{c}": f"{c}_image" for c in spec.cameras}, (STATE, spec.lowdim_keys))

    @classmethod
    def parse(cls, spec: TaskSpec, items: list[str] | tuple[str, ...] = ()) -> "KeyMap":
        """The default map changed by ``lerobot_key=spec_key`` items: an image key, ``action``, ``states``, or
        low-dim keys (comma separated, concatenated in the given order) for a state vector."""
        km = cls.default(spec)
        images = dict(km.images)
        for item in items:
            if "=" not in item:
                raise LeRobotError(f"--map {item!r} is not LEROBOT_KEY=SPEC_KEY (e.g. "
                                   f"observation.images.front={spec.image_keys[0]})")
            source, target = (part.strip() for part in item.split("=", 1))
            targets = tuple(t.strip() for t in target.split(",") if t.strip())
            if target in spec.image_keys:
                images = {k: v for k, v in images.items() if v != target}
                images[source] = target
            elif target == "action":
                km.action = source
            elif target == "states":
                km.env_state = source
            elif targets and all(t in spec.lowdim_keys for t in targets):
                km.state = (source, targets)
            else:
                raise LeRobotError(f"--map {item!r}: {target!r} is not a key of task {spec.name} (images "
                                   f"{list(spec.image_keys)}, low-dim {list(spec.lowdim_keys)}, action, states)")
        km.images = images
        return km


def instruction_for(spec: TaskSpec) -> str:
    """The default task string of an exported episode: the source task's words (LIBERO names carry them)."""
    words = spec.source_task.split("_")
    while words and (words[0].isupper() or words[0].rstrip("0123456789").isupper()):   # LIBERO's SCENE prefix
        words = words[1:]
    return " ".join(words) if len(words) > 1 else spec.name


# ----------------------------------------------------------------------------- statistics


class RunningStats:
    """min, max, mean, std over the rows of one vector feature, combined episode by episode; quantiles from the
    values themselves (vector features are small) or, for uint8 images, exactly from 256-bin histograms."""

    def __init__(self, image: bool = False):
        self.image = image
        self.count = 0
        self.mean = self.m2 = self.min = self.max = None
        self.values: list[np.ndarray] = []
        self.histogram: np.ndarray | None = None

    def add(self, x: np.ndarray) -> dict:
        """Add one episode's rows (T, D) or frames (T, H, W, 3); returns that episode's own statistics."""
        if self.image:
            hist = np.stack([np.bincount(x[..., c].ravel(), minlength=256) for c in range(x.shape[-1])])
            self.histogram = hist if self.histogram is None else self.histogram + hist
            flat = x.reshape(-1, x.shape[-1]).astype(np.float64) / 255.0
            episode = _moments(flat)
            episode.update(_hist_quantiles(hist))
            episode = {k: (np.asarray(v).reshape(-1, 1, 1) if k != "count" else v) for k, v in episode.items()}
        else:
            flat = x.reshape(len(x), -1).astype(np.float64)
            self.values.append(flat)
            episode = _moments(flat)
            episode.update({f"q{int(round(q * 100)):02d}": np.quantile(flat, q, axis=0) for q in QUANTILES})
        n, mean, m2 = episode["count"][0], _flat(episode["mean"]), _flat(episode["m2"])
        if self.count == 0:
            self.mean, self.m2 = mean, m2
            self.min, self.max = _flat(episode["min"]), _flat(episode["max"])
        else:   # Chan et al.: combine two (count, mean, M2) summaries
            total = self.count + n
            delta = mean - self.mean
            self.mean = self.mean + delta * n / total
            self.m2 = self.m2 + m2 + delta ** 2 * self.count * n / total
            self.min, self.max = np.minimum(self.min, _flat(episode["min"])), np.maximum(self.max, _flat(episode["max"]))
        self.count += n
        episode.pop("m2")
        return episode

    def result(self) -> dict:
        out = {"min": self.min, "max": self.max, "mean": self.mean, "std": np.sqrt(self.m2 / self.count),
               "count": np.array([self.count])}
        if self.image:
            out.update(_hist_quantiles(self.histogram))
            return {k: (np.asarray(v).reshape(-1, 1, 1) if k != "count" else v) for k, v in out.items()}
        values = np.concatenate(self.values)
        out.update({f"q{int(round(q * 100)):02d}": np.quantile(values, q, axis=0) for q in QUANTILES})
        return out


def _flat(v) -> np.ndarray:
    return np.asarray(v, np.float64).reshape(-1)


def _moments(flat: np.ndarray) -> dict:
    mean = flat.mean(axis=0)
    return {"min": flat.min(axis=0), "max": flat.max(axis=0), "mean": mean, "std": flat.std(axis=0),
            "count": np.array([len(flat)]), "m2": ((flat - mean) ** 2).sum(axis=0)}


def _hist_quantiles(hist: np.ndarray) -> dict:
    """Exact quantiles of uint8 values per channel from their 256-bin counts, in [0, 1]."""
    cdf = np.cumsum(hist, axis=1) / hist.sum(axis=1, keepdims=True)
    return {f"q{int(round(q * 100)):02d}": np.argmax(cdf >= q, axis=1) / 255.0 for q in QUANTILES}


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


# ----------------------------------------------------------------------------- video


class VideoWriter:
    """One camera's video files: episodes appended one after the other, a new file past VIDEO_FILE_MB.

    The encoder runs on a watched thread: one that takes no frame and hands back no packet for ``timeout_s``
    has stalled (a C library call cannot be interrupted), and the export stops with the episode and the fix
    instead of waiting for good."""

    def __init__(self, root: Path, key: str, fps: int, codec: str, height: int, width: int,
                 timeout_s: float = ENCODER_TIMEOUT_S):
        self.root, self.key, self.fps, self.codec = root, key, fps, codec
        self.height, self.width = height, width
        self.timeout_s = timeout_s
        self.chunk = self.file = 0
        self.container = None
        self.frames = 0          # frames in the current file
        self.bytes = 0           # bytes muxed into it (the encoder may hold frames back: not the file's size yet)
        self.progress = 0        # frames sent and packets muxed, ever: what the watch looks at
        self.stalled = False
        self.episode = -1        # the episode being encoded (or the last one, while flushing)
        self.last_dts: int | None = None

    def _open(self) -> None:
        encoder, pix_fmt, options = CODECS[self.codec]
        path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.chunk, file_index=self.file)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.container = av.open(str(path), "w")
        self.stream = self.container.add_stream(encoder, rate=self.fps)
        self.stream.width, self.stream.height, self.stream.pix_fmt = self.width, self.height, pix_fmt
        self.stream.time_base = Fraction(1, self.fps)
        self.stream.options = dict(options)
        self.frames = self.bytes = 0
        self.last_dts = None

    def add_episode(self, frames: np.ndarray, episode: int) -> dict:
        """Encode one episode's (T, H, W, 3) uint8 frames; returns its LeRobot episode columns."""
        if self.container is not None and self.bytes / 2**20 >= VIDEO_FILE_MB:
            self.close()
            self.chunk, self.file = _next_file(self.chunk, self.file)
        if self.container is None:
            self._open()
        start = self.frames
        self.episode = episode
        self._watched(lambda: self._encode(frames), f"encoding episode {episode}")
        return {f"videos/{self.key}/chunk_index": self.chunk, f"videos/{self.key}/file_index": self.file,
                f"videos/{self.key}/from_timestamp": start / self.fps,
                f"videos/{self.key}/to_timestamp": self.frames / self.fps}

    def _encode(self, frames: np.ndarray) -> None:
        for frame in frames:
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            vf.pts, vf.time_base = self.frames, Fraction(1, self.fps)
            self.frames += 1
            self.progress += 1
            for packet in self.stream.encode(vf):
                self._mux(packet)

    def _mux(self, packet) -> None:
        if self.last_dts is not None and packet.dts is not None and packet.dts <= self.last_dts:
            raise LeRobotError(f"the {CODECS[self.codec][0]} encoder of {self.key} handed out frame {packet.dts} "
                               f"after frame {self.last_dts} (episode {self.episode}); packets out of decoding order "
                               "cannot be stored: export again, or with --codec lossless or h264")
        self.last_dts = packet.dts
        self.bytes += packet.size
        self.progress += 1
        self.container.mux(packet)

    def _watched(self, job, what: str) -> None:
        """Run ``job`` on a daemon thread; raise (leaving the thread behind) if it makes no progress for
        ``timeout_s``, and re-raise what it raised."""
        failure: list[BaseException] = []

        def run() -> None:
            try:
                job()
            except BaseException as exc:   # handed to the caller's thread below
                failure.append(exc)

        thread = threading.Thread(target=run, name=f"encoder {self.key}", daemon=True)
        seen = self.progress
        thread.start()
        while True:
            thread.join(self.timeout_s)
            if not thread.is_alive():
                break
            if self.progress == seen:
                self.stalled = True
                raise LeRobotError(f"the {CODECS[self.codec][0]} encoder of {self.key} made no progress for "
                                   f"{self.timeout_s:g} s while {what}; it has stalled (nothing was written): "
                                   f"export again, or with --codec lossless or h264 (or a longer "
                                   f"--encoder-timeout when frames are large)")
            seen = self.progress
        if failure:
            raise failure[0]

    def close(self) -> None:
        """Flush the encoder (the frames it still holds) and close the current file."""
        if self.container is not None:
            self._watched(self._flush, f"flushing the frames it held after episode {self.episode}")
            self.container.close()
            self.container = None

    def _flush(self) -> None:
        for packet in self.stream.encode():
            self._mux(packet)

    def discard(self) -> None:
        """Give up the current file without flushing (the export failed); a stalled encoder is left alone."""
        if self.container is not None and not self.stalled:
            self.container.close()
        self.container = None

    def info(self) -> dict:
        """The feature's ``info`` as LeRobot's ``get_video_info`` reads it from the file."""
        path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=0, file_index=0)
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            return {"video.height": stream.height, "video.width": stream.width,
                    "video.codec": stream.codec_context.codec.canonical_name, "video.pix_fmt": stream.pix_fmt,
                    "video.is_depth_map": False, "video.fps": self.fps, "video.channels": 3, "has_audio": False}


def _next_file(chunk: int, file: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == CHUNKS_SIZE - 1 else (chunk, file + 1)


class VideoReader:
    """Frames of a camera's video files in time order, handed out episode by episode (sequential decode)."""

    def __init__(self, root: Path, key: str):
        self.root, self.key = root, key
        self.open_path: Path | None = None
        self.frames: Iterator | None = None
        self.pending: tuple[float, np.ndarray] | None = None

    def _file(self, chunk: int, file: int) -> Path:
        return self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=chunk, file_index=file)

    def episode(self, chunk: int, file: int, start: float, end: float, length: int, episode: int) -> np.ndarray:
        path = self._file(chunk, file)
        rel = path.relative_to(self.root)
        if path != self.open_path:
            if not path.is_file():
                raise LeRobotError(f"{rel} is missing (episode {episode} of {self.key} lies in it); download the "
                                   "dataset's videos folder whole")
            try:
                container = av.open(str(path))
                stream = container.streams.video[0]
            except (av.error.FFmpegError, IndexError) as exc:
                raise LeRobotError(f"{rel} is not a readable video ({exc}); re-download or re-encode it") from None
            stream.thread_type = "AUTO"

            def frames(container=container, stream=stream):
                try:
                    for frame in container.decode(stream):
                        yield float(frame.pts * stream.time_base), frame.to_ndarray(format="rgb24")
                except av.error.FFmpegError as exc:
                    raise LeRobotError(f"{rel} is damaged ({exc}); re-download or re-encode it") from None
                finally:
                    container.close()
            self.open_path, self.frames, self.pending = path, frames(), None
        out = []
        while len(out) < length:
            item = self.pending if self.pending is not None else next(self.frames, None)
            self.pending = None
            if item is None or item[0] >= end - TOLERANCE_S:
                self.pending = item
                raise LeRobotError(f"{rel} holds {len(out)} frames of episode {episode} ({start:.3f} s to "
                                   f"{end:.3f} s) but the episode has {length} rows; the video is shorter than "
                                   "its episode: re-encode it from the episode's frames")
            if item[0] >= start - TOLERANCE_S:
                out.append(item[1])
        return np.stack(out)


# ----------------------------------------------------------------------------- export


def export_lerobot(src: str | Path, out_dir: str | Path, task: str | None = None, fps: int | None = None,
                   codec: str = "lossless", instruction: str | None = None, robot_type: str | None = None,
                   encoder_timeout_s: float = ENCODER_TIMEOUT_S) -> dict:
    """Write a robomimic-layout demos (or rollouts) file as a LeRobotDataset v3.0 folder; returns a summary.
    An encoder that makes no progress for ``encoder_timeout_s`` stops the export with the episode it was on."""
    if codec not in CODECS:
        raise LeRobotError(f"codec {codec!r} is not one of {sorted(CODECS)}")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise LeRobotError(f"{out} exists and is not empty; pass a new folder (nothing was written)")
    with open_hdf5(src) as f:
        if "data" not in f or not demo_names(f["data"]):
            raise LeRobotError(f"{src} holds no data/demo_N episodes; write demos with `jepa-envs make-demos`")
        env_args = json.loads(f["data"].attrs.get("env_args", "{}"))
        spec = resolve_task(task, env_args, src)
        fps = int(fps or round(spec.control_hz))
        if fps <= 0:
            raise LeRobotError(f"--fps must be a positive number of frames per second, got {fps}")
        names = demo_names(f["data"])
        first = f["data"][names[0]]
        features = _export_features(spec, first, src)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent if out.parent.exists() else None))
        try:
            summary = _write_export(f, names, spec, features, tmp, fps, codec, instruction, robot_type,
                                    encoder_timeout_s)
            if out.exists():
                out.rmdir()
            tmp.rename(out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return {**summary, "out": str(out)}


def _export_features(spec: TaskSpec, demo, src) -> dict:
    obs = demo["obs"]
    features: dict = {}
    for cam in spec.cameras:
        key = f"{cam}_image"
        if key not in obs:
            raise LeRobotError(f"{src}: data/demo_0/obs has no {key!r} (task {spec.name} needs it); for a file "
                               "with states only, render it first: jepa-envs render-dataset")
        _, h, w, c = obs[key].shape
        features[f"{IMAGES}{cam}"] = {"dtype": "video", "shape": [h, w, c], "names": ["height", "width", "channels"]}
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
                  encoder_timeout_s: float) -> dict:
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
        for e, name in enumerate(names):
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
                data_chunk, data_file = _next_file(data_chunk, data_file)
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
                frames = obs[f"{key[len(IMAGES):]}_image"][()]
                if frames.shape[0] != n or frames.dtype != np.uint8:
                    raise LeRobotError(f"data/{name}/obs/{key[len(IMAGES):]}_image has shape {frames.shape} "
                                       f"{frames.dtype}; it needs {n} uint8 frames")
                row.update(video.add_episode(frames, e))
                row.update(_episode_stats(key, stats[key].add(frames)))
            for key in vectors:   # LeRobot keeps statistics of every feature, the frame counters included
                row.update(_episode_stats(key, stats[key].add(columns[key].reshape(n, -1))))
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
    _write_meta(root, features, episodes, tasks, stats, fps, robot_type or f"jepa/{spec.name}")
    return {"episodes": len(episodes), "frames": index, "tasks": list(tasks), "fps": fps, "codec": codec,
            "task": spec.name}


def _episode_stats(key: str, stats: dict) -> dict:
    return {f"stats/{key}/{name}": np.asarray(value).tolist() for name, value in stats.items()}


def _write_meta(root: Path, features, episodes, tasks, stats, fps, robot_type) -> None:
    path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(episodes), str(path), compression="snappy")
    _write_tasks(root, tasks)
    (root / STATS_PATH).write_text(json.dumps(_jsonable({k: s.result() for k, s in stats.items()}), indent=4))
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


# ----------------------------------------------------------------------------- import


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
    return (Path(path) / INFO_PATH).is_file()


def open_lerobot(root: str | Path) -> LeRobotDataset:
    """Read and check a LeRobot dataset's metadata (codebase version, files, totals)."""
    root = Path(root)
    info_path = root / INFO_PATH
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
        raise LeRobotError(f"{TASKS_PATH} is not a readable parquet file ({_short(exc)}); re-download it") from None
    tasks = _task_strings(tasks_table)
    episodes = []
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise LeRobotError(f"{root}/meta/episodes has no chunk-*/file-*.parquet; download the meta folder whole")
    for path in files:
        try:
            episodes += pq.read_table(str(path)).to_pylist()
        except Exception as exc:
            raise LeRobotError(f"{path.relative_to(root)} is not a readable parquet file ({_short(exc)}); "
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


def _short(exc: Exception) -> str:
    return first_line(str(exc) or type(exc).__name__)


def _check_features(ds: LeRobotDataset, spec: TaskSpec, km: KeyMap, fps: int | None) -> None:
    feats = ds.features
    if fps is None and ds.fps != round(spec.control_hz):
        raise LeRobotError(f"the dataset records at {ds.fps} fps, task {spec.name} acts at {spec.control_hz:g} Hz; "
                           f"pass --fps {ds.fps} to accept it (the policy's timing follows the data)")
    needed = {**{k: "image" for k in km.images}, km.state[0]: "state", km.action: "action"}
    for key, what in needed.items():
        if key not in feats:
            have = ", ".join(sorted(k for k in feats if k not in DEFAULT_FEATURES))
            raise LeRobotError(f"the dataset has no feature {key!r} ({what} of task {spec.name}); it has: {have}. "
                               f"Map one with --map {'FEATURE=' + (km.images.get(key) or 'KEY')}")
    for key, target in km.images.items():
        ft = feats[key]
        if ft.get("dtype") not in ("video", "image") or len(ft.get("shape", [])) != 3 or ft["shape"][-1] != 3:
            raise LeRobotError(f"feature {key!r} is {ft.get('dtype')} {ft.get('shape')}; {target} needs RGB images "
                               "(video or image, shape [H, W, 3])")
    missing = set(spec.image_keys) - set(km.images.values())
    if missing:
        raise LeRobotError(f"task {spec.name} needs camera key(s) {sorted(missing)} and no feature maps to them; "
                           f"pass --map observation.images.NAME={sorted(missing)[0]}")
    state_dim = sum(dict(spec.lowdim)[k] for k in km.state[1])
    if list(feats[km.state[0]].get("shape", [])) != [state_dim]:
        raise LeRobotError(f"feature {km.state[0]!r} has shape {feats[km.state[0]].get('shape')}; task {spec.name}'s "
                           f"{list(km.state[1])} need [{state_dim}]; map the right feature with --map "
                           f"FEATURE={','.join(km.state[1])}")
    if set(km.state[1]) != set(spec.lowdim_keys):
        raise LeRobotError(f"the state map gives {list(km.state[1])}; task {spec.name} needs all of "
                           f"{list(spec.lowdim_keys)}")
    action_dim = feats[km.action].get("shape")
    if list(action_dim or []) != [spec.action_dim]:
        raise LeRobotError(f"feature {km.action!r} has shape {action_dim}; task {spec.name} acts with "
                           f"{spec.action_dim}-D absolute actions")


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
                raise LeRobotError(f"{rel} is not a readable parquet file ({_short(exc)}); re-download it") from None

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


def import_lerobot(root: str | Path, out: str | Path, task: str, key_map: list[str] | tuple[str, ...] = (),
                   fps: int | None = None) -> dict:
    """Convert a LeRobot v3.0 dataset into a robomimic-layout HDF5 file the loader reads; returns a summary."""
    try:
        spec = get_task_spec(task)
    except KeyError as exc:
        raise LeRobotError(exc.args[0]) from None
    ds = open_lerobot(root)
    km = KeyMap.parse(spec, key_map)
    _check_features(ds, spec, km, fps)
    env_args = {"env_name": spec.name, "type": "lerobot",
                "env_kwargs": {"image_size": int(ds.features[next(iter(km.images))]["shape"][0])},
                "lerobot": {"root": str(Path(root).resolve()), "fps": ds.fps,
                            "robot_type": ds.info.get("robot_type"), "map": _jsonable(km.__dict__)}}
    frames = 0
    with DemoWriter(out, env_args) as writer:   # an error anywhere leaves no file at ``out``
        for episode in iter_episodes(ds, spec, km):
            writer.add(episode)
            frames += len(episode["actions"])
        if frames != ds.info["total_frames"]:
            raise LeRobotError(f"info.json says {ds.info['total_frames']} frames, the episodes hold {frames}; "
                               "re-download the dataset")
    return {"episodes": len(ds.episodes), "frames": frames, "task": spec.name, "fps": ds.fps, "out": str(out)}



def resolve_dataset(path: str | Path, task: str, key_map: list[str] | tuple[str, ...] = ()) -> Path:
    """The HDF5 file to train from: ``path`` itself, or for a LeRobot v3.0 root its import, made once and kept
    in the dataset cache (keyed by the root, its files' sizes and times, the task and the map)."""
    path = Path(path).expanduser()
    if not is_lerobot_root(path):
        if key_map:
            raise LeRobotError(f"a dataset map applies to LeRobot datasets; {path} is not one (no {INFO_PATH})")
        return path
    root = path.resolve()
    files = sorted(p for p in root.rglob("*") if p.is_file())
    digest = hashlib.sha1(json.dumps([str(root), task, sorted(key_map)] + [
        [str(p.relative_to(root)), p.stat().st_size, p.stat().st_mtime_ns] for p in files]).encode()).hexdigest()[:16]
    out = default_cache_dir() / "lerobot" / f"{root.name}-{task}-{digest}.hdf5"
    if not out.is_file():
        import_lerobot(root, out, task, key_map)
    return out


def bench_lerobot(src: str | Path, codec: str = "lossless") -> dict:
    """Frames/s and peak memory of export and import beside an h5py read of the same frames, each phase in a
    fresh process (its own peak RSS), in one run."""
    import os
    import subprocess
    import sys

    src = Path(src).resolve()
    work = Path(tempfile.mkdtemp(prefix="jepa-lerobot-bench-"))
    phases = {
        "h5py read": f"import h5py\nfrom jepa_envs.datasets.hdf5 import demo_names\nf = h5py.File({str(src)!r})\n"
                     "n = 0\nfor d in demo_names(f['data']):\n    for k in f['data'][d]['obs']:\n"
                     "        x = f['data'][d]['obs'][k][()]\n        n += len(x) if x.dtype.name == 'uint8' else 0\n"
                     "frames = n",
        "export": f"from jepa_envs.datasets.lerobot_format import export_lerobot\n"
                  f"frames = export_lerobot({str(src)!r}, {str(work / 'ds')!r}, codec={codec!r})['frames']",
        "import": f"from jepa_envs.datasets.lerobot_format import import_lerobot, open_lerobot\n"
                  f"task = open_lerobot({str(work / 'ds')!r}).info['robot_type'].split('/')[-1]\n"
                  f"frames = import_lerobot({str(work / 'ds')!r}, {str(work / 'back.hdf5')!r}, task)['frames']",
    }
    out = {"src": str(src), "codec": codec, "load_average": os.getloadavg()[0], "phases": {}}
    try:
        for name, code in phases.items():
            script = ("import json, resource, time\nt0 = time.perf_counter()\n" + code + "\n"
                      "print(json.dumps({'frames': frames, 'seconds': time.perf_counter() - t0, "
                      "'peak_rss_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))")
            done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
            row = json.loads(done.stdout.strip().splitlines()[-1])
            row["frames_per_s"] = row["frames"] / row["seconds"]
            out["phases"][name] = row
        out["dataset_mib"] = sum(p.stat().st_size for p in (work / "ds").rglob("*") if p.is_file()) / 2**20
        out["hdf5_mib"] = src.stat().st_size / 2**20
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out
