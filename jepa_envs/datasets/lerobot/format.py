"""LeRobotDataset v3.0's layout as LeRobot writes it: paths, sizes, default features, our key conventions, the
video codecs, and the map from another dataset's feature names to a task spec's keys."""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from jepa_envs.errors import first_line
from jepa_envs.tasks.spec import TaskSpec

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
ROBOT_TYPE_PREFIX = "jepa/"    # our exports' robot_type is jepa/<task>: import finds the task from it
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


@dataclass
class KeyMap:
    """Which LeRobot feature fills which of the task spec's keys."""

    images: dict[str, str]                 # LeRobot image/video feature -> spec image key
    state: tuple[str, tuple[str, ...]]     # (LeRobot vector feature, spec low-dim keys it concatenates in order)
    action: str = ACTION
    env_state: str | None = ENV_STATE      # -> ``states`` (simulator state) when the dataset has it

    @classmethod
    def default(cls, spec: TaskSpec) -> "KeyMap":
        return cls(image_features(spec), (STATE, spec.lowdim_keys))

    @classmethod
    def parse(cls, spec: TaskSpec, items: list[str] | tuple[str, ...] = (), flag: str = "--map") -> "KeyMap":
        """The default map changed by ``lerobot_key=spec_key`` items: an image key, ``action``, ``states``, or
        low-dim keys (comma separated, concatenated in the given order) for a state vector. ``flag``: the option
        the items came from, named in refusals (``map_option``)."""
        km = cls.default(spec)
        images = dict(km.images)
        for item in items:
            if "=" not in item:
                raise LeRobotError(f"{flag} {item!r} is not LEROBOT_KEY=SPEC_KEY (e.g. "
                                   f"{map_option('observation.images.front', spec.image_keys[0], flag)})")
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
                raise LeRobotError(f"{map_option(source, target, flag)}: {target!r} is not a key of task {spec.name} "
                                   f"(images {list(spec.image_keys)}, low-dim {list(spec.lowdim_keys)}, action, "
                                   "states)")
        km.images = images
        return km


def image_features(spec: TaskSpec) -> dict[str, str]:
    """LeRobot image feature -> our image key of a task: ``observation.images.<camera>``, or the names its spec
    gives (PushTStandard: lerobot/pusht's single ``observation.image``)."""
    return dict(spec.extra.get("lerobot_image_keys") or {f"{IMAGES}{c}": f"{c}_image" for c in spec.cameras})


def map_option(source: str, target: str, flag: str = "--map") -> str:
    """How a user maps one feature to one of our keys with ``flag``: ``jepa-envs lerobot import``'s
    ``--map F=K``, or ``jepa-policy train``'s ``--dataset-map`` (a JSON object)."""
    if flag == "--dataset-map":
        return f"--dataset-map '{json.dumps({source: target})}'"
    return f"{flag} {source}={target}"


def instruction_for(spec: TaskSpec) -> str:
    """The default task string of an exported episode: the one the task's public dataset uses
    (``lerobot_task``: lerobot/pusht's for the standard PushT), else the source task's words (LIBERO names carry
    them), else the task's name (a gym id such as gym_pusht/PushT-v0 is not words)."""
    if spec.extra.get("lerobot_task"):
        return spec.extra["lerobot_task"]
    if "/" in spec.source_task:
        return spec.name
    words = spec.source_task.split("_")
    while words and (words[0].isupper() or words[0].rstrip("0123456789").isupper()):   # LIBERO's SCENE prefix
        words = words[1:]
    return " ".join(words) if len(words) > 1 else spec.name


def next_file(chunk: int, file: int) -> tuple[int, int]:
    """The (chunk, file) index after this one: CHUNKS_SIZE files to a chunk folder."""
    return (chunk + 1, 0) if file == CHUNKS_SIZE - 1 else (chunk, file + 1)


def short_error(exc: Exception) -> str:
    """A library error's first line (their messages run on for paragraphs)."""
    return first_line(str(exc) or type(exc).__name__)


def jsonable(value):
    """``value`` with numpy arrays and scalars turned into lists and Python numbers, for json.dumps."""
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
