"""Whether a LeRobot dataset can fill a task spec's keys through a key map (features, shapes, rate), every
problem found at once, and which of its features the map leaves out."""
from __future__ import annotations

from jepa_envs.datasets.lerobot.format import (DEFAULT_FEATURES, DONE, REWARD, SUCCESS, KeyMap, LeRobotError,
                                               map_option)
from jepa_envs.datasets.lerobot.reader import LeRobotDataset
from jepa_envs.tasks.pusht_variants import demonstration_mismatches
from jepa_envs.tasks.spec import TaskSpec


def check_features(ds: LeRobotDataset, spec: TaskSpec, km: KeyMap, fps: int | None,
                   fps_fix: str | None = None, map_flag: str = "--map") -> None:
    """Raise one LeRobotError naming every way the dataset does not fit the task (each with its fix).

    ``fps`` is the rate the user accepted (it must be the dataset's own); ``fps_fix`` words the fix for a rate
    other than the task's where ``--fps`` is not the caller's option (``{fps}`` in it: the dataset's rate);
    ``map_flag``: the caller's option for a key map (``map_option``)."""
    problems = []
    if fps is not None and fps != ds.fps:
        problems.append(f"--fps {fps} is not the dataset's rate ({ds.fps} fps in info.json); pass --fps {ds.fps} "
                        "or leave it out")
    elif fps is None and ds.fps != round(spec.control_hz):
        fix = (fps_fix or "pass --fps {fps} to accept it (the policy's timing follows the data)").replace(
            "{fps}", str(ds.fps))
        problems.append(f"the dataset records at {ds.fps} fps, task {spec.name} acts at {spec.control_hz:g} Hz; {fix}")
    feats = ds.features
    have = ", ".join(sorted(k for k in feats if k not in DEFAULT_FEATURES))
    needed = {**{k: "image" for k in km.images}, km.state[0]: "state", km.action: "action"}
    absent = [key for key in needed if key not in feats]
    for key in absent:
        problems.append(f"the dataset has no feature {key!r} ({needed[key]} of task {spec.name}); map one of its "
                        f"features with {map_option('FEATURE', km.images.get(key) or _target(km, key), map_flag)}")
    if absent:
        problems[-1] += f" (the dataset's features: {have})"
    for key, target in km.images.items():
        ft = feats.get(key)
        if ft is not None and (ft.get("dtype") not in ("video", "image") or len(ft.get("shape", [])) != 3
                               or ft["shape"][-1] != 3):
            problems.append(f"feature {key!r} is {ft.get('dtype')} {ft.get('shape')}; {target} needs RGB images "
                            "(video or image, shape [H, W, 3])")
    missing = set(spec.image_keys) - set(km.images.values())
    if missing:
        problems.append(f"task {spec.name} needs camera key(s) {sorted(missing)} and no feature maps to them; "
                        f"pass {map_option('observation.images.NAME', sorted(missing)[0], map_flag)}")
    state_dim = sum(dict(spec.lowdim)[k] for k in km.state[1])
    if km.state[0] in feats and list(feats[km.state[0]].get("shape", [])) != [state_dim]:
        problems.append(f"feature {km.state[0]!r} has shape {feats[km.state[0]].get('shape')}; task {spec.name}'s "
                        f"{list(km.state[1])} need [{state_dim}]; map the right feature with "
                        f"{map_option('FEATURE', ','.join(km.state[1]), map_flag)}")
    if set(km.state[1]) != set(spec.lowdim_keys):
        problems.append(f"the state map gives {list(km.state[1])}; task {spec.name} needs all of "
                        f"{list(spec.lowdim_keys)}")
    if km.action in feats and list(feats[km.action].get("shape") or []) != [spec.action_dim]:
        problems.append(f"feature {km.action!r} has shape {feats[km.action].get('shape')}; task {spec.name} acts "
                        f"with {spec.action_dim}-D absolute actions")
    # a PushT dataset of the other variant, or in other units (image size, action units)
    problems += demonstration_mismatches(spec, {k: feats[k].get("shape") for k in km.images if k in feats}, feats,
                                         _episode_ranges(ds, km.action), _episode_ranges(ds, km.state[0]))
    if problems:
        count = f"{len(problems)} problems" if len(problems) > 1 else "1 problem"
        raise LeRobotError(f"{ds.root} does not fit task {spec.name} ({count}): " + "; ".join(problems))


def _episode_ranges(ds: LeRobotDataset, key: str) -> list[tuple[list, list]] | None:
    """Per episode, the (min, max) per dimension of a feature, from the episodes' stats (None without them)."""
    ranges = [(ep.get(f"stats/{key}/min"), ep.get(f"stats/{key}/max")) for ep in ds.episodes]
    return None if not ranges or any(lo is None or hi is None for lo, hi in ranges) else ranges


def _target(km: KeyMap, key: str) -> str:
    return ",".join(km.state[1]) if key == km.state[0] else "action"


def unmapped_features(ds: LeRobotDataset, km: KeyMap) -> dict[str, str]:
    """The dataset's features an import leaves out (no spec key takes them), each as ``dtype [shape]``."""
    used = {*km.images, km.state[0], km.action, km.env_state, REWARD, DONE, SUCCESS, *DEFAULT_FEATURES}
    return {key: f"{ft.get('dtype')} {ft.get('shape')}" for key, ft in ds.features.items() if key not in used}
