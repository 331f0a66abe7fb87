"""Import: a LeRobotDataset v3.0 root -> a robomimic-layout HDF5 file the loader and trainer read (also made on
demand, once, for `jepa-policy train --dataset ROOT`)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from tqdm import tqdm

from jepa_envs.datasets.hdf5 import DatasetError, DemoWriter, default_cache_dir, open_hdf5, task_for_env_name
from jepa_envs.datasets.lerobot.checks import check_features, unmapped_features
from jepa_envs.datasets.lerobot.format import INFO_PATH, ROBOT_TYPE_PREFIX, KeyMap, LeRobotError, jsonable
from jepa_envs.datasets.lerobot.reader import LeRobotDataset, is_lerobot_root, iter_episodes, open_lerobot
from jepa_envs.tasks.spec import TaskSpec, all_task_specs, get_task_spec


def import_lerobot(root: str | Path, out: str | Path, task: str | None = None,
                   key_map: list[str] | tuple[str, ...] = (), fps: int | None = None, overwrite: bool = False,
                   fps_fix: str | None = None, map_flag: str = "--map", progress: bool = False) -> dict:
    """Convert a LeRobot v3.0 dataset into a robomimic-layout HDF5 file the loader reads; returns a summary
    (``unmapped``: the dataset's features no spec key took, with their dtype and shape).

    ``task`` defaults to the one the dataset names (our exports' ``robot_type`` is ``jepa/<task>``); ``fps``
    accepts a dataset recorded at another rate than the task's (it must be the dataset's own); an existing
    ``out`` is replaced only with ``overwrite``; ``map_flag``: the caller's option for ``key_map``, named in
    refusals (``jepa-policy train`` calls it --dataset-map); ``progress``: a bar of the episodes on stderr."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise LeRobotError(f"{out} exists; pass another path, or --overwrite to replace it (nothing was written)")
    if not out.parent.is_dir():
        raise LeRobotError(f"{out.parent} does not exist; create it first (nothing was written)")
    ds = open_lerobot(root)
    spec = _task_of(ds, task)
    km = KeyMap.parse(spec, key_map, map_flag)
    check_features(ds, spec, km, fps, fps_fix, map_flag)
    env_args = {"env_name": spec.name, "type": "lerobot",
                "env_kwargs": {"image_size": int(ds.features[next(iter(km.images))]["shape"][0])},
                "lerobot": {"root": str(Path(root).resolve()), "fps": ds.fps,
                            "robot_type": ds.info.get("robot_type"), "map": jsonable(km.__dict__)}}
    frames = 0
    with DemoWriter(out, env_args) as writer:   # an error anywhere leaves no file at ``out``
        for episode in tqdm(iter_episodes(ds, spec, km), total=len(ds.episodes), desc="lerobot import", unit="episode",
                            disable=not progress):
            writer.add(episode)
            frames += len(episode["actions"])
        if frames != ds.info["total_frames"]:
            raise LeRobotError(f"info.json says {ds.info['total_frames']} frames, the episodes hold {frames}; "
                               "re-download the dataset")
    return {"episodes": len(ds.episodes), "frames": frames, "task": spec.name, "fps": ds.fps, "out": str(out),
            "unmapped": unmapped_features(ds, km)}


def _task_of(ds: LeRobotDataset, task: str | None) -> TaskSpec:
    if task is not None:
        try:
            return get_task_spec(task)
        except KeyError as exc:
            raise LeRobotError(exc.args[0]) from None
    robot_type = str(ds.info.get("robot_type") or "")
    named = robot_type[len(ROBOT_TYPE_PREFIX):] if robot_type.startswith(ROBOT_TYPE_PREFIX) else None
    names = {spec.name for spec in all_task_specs()}
    if named not in names:
        raise LeRobotError(f"{ds.root} names no task of ours (robot_type {robot_type or None!r}); pass --task with "
                           f"the task its data is for (one of: {', '.join(sorted(names))})")
    return get_task_spec(named)


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
        out.parent.mkdir(parents=True, exist_ok=True)
        maps = "".join(f" --map {item}" for item in key_map)
        # training has no rate option: a dataset at another rate is imported by hand, its rate accepted there
        fps_fix = (f"import it with its rate accepted (jepa-envs lerobot import {root} OUT.hdf5 --task {task}"
                   f"{maps} --fps {{fps}}) and train with --dataset OUT.hdf5")
        import_lerobot(root, out, task, key_map, fps_fix=fps_fix, map_flag="--dataset-map")
    return out


def recorded_task(path: str | Path) -> str | None:
    """The task a dataset says it holds: a LeRobot root's ``robot_type`` jepa/<task> (our exports), an HDF5
    file's env_args ``env_name``; None when it names none of ours or cannot be read here (loading it says why)."""
    path = Path(path).expanduser()
    if is_lerobot_root(path):
        robot_type = str(json.loads((path / INFO_PATH).read_text()).get("robot_type") or "")
        named = robot_type[len(ROBOT_TYPE_PREFIX):] if robot_type.startswith(ROBOT_TYPE_PREFIX) else ""
        return named if named in {spec.name for spec in all_task_specs()} else None
    try:
        with open_hdf5(path) as f:
            raw = f["data"].attrs.get("env_args") if "data" in f else None
        found = task_for_env_name(str(json.loads(raw).get("env_name", ""))) if raw is not None else None
    except (DatasetError, ValueError, AttributeError):
        return None
    return found.name if found is not None else None
