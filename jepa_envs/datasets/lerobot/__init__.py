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

One layer per module: ``format`` (the layout's paths and constants, our key conventions, codecs, the key map),
``stats`` (meta/stats.json), ``video`` (the watched encoder, the sequential decoder), ``writer`` (export),
``reader`` (open a root, episodes one at a time), ``checks`` (a dataset against a task spec), ``importer``
(import, and a root made trainable on demand) and ``bench``.
"""
from __future__ import annotations

from jepa_envs.datasets.lerobot.bench import bench_lerobot
from jepa_envs.datasets.lerobot.format import CODEBASE_VERSION, CODECS, KeyMap, LeRobotError
from jepa_envs.datasets.lerobot.importer import import_lerobot, recorded_task, resolve_dataset
from jepa_envs.datasets.lerobot.reader import LeRobotDataset, is_lerobot_root, iter_episodes, open_lerobot
from jepa_envs.datasets.lerobot.writer import export_lerobot

__all__ = ["CODEBASE_VERSION", "CODECS", "KeyMap", "LeRobotDataset", "LeRobotError", "bench_lerobot",
           "export_lerobot", "import_lerobot", "is_lerobot_root", "iter_episodes", "open_lerobot", "recorded_task",
           "resolve_dataset"]
