"""Whether a LeRobot dataset can fill a task spec's keys through a key map (features, shapes, rate)."""
from __future__ import annotations

from jepa_envs.datasets.lerobot.format import DEFAULT_FEATURES, KeyMap, LeRobotError
from jepa_envs.datasets.lerobot.reader import LeRobotDataset
from jepa_envs.tasks.spec import TaskSpec


def check_features(ds: LeRobotDataset, spec: TaskSpec, km: KeyMap, fps: int | None) -> None:
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
