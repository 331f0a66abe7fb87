"""robomimic PH tasks (Lift, Can, Square, ToolHang, Transport) on robosuite 1.4.1, behind our Gymnasium interface.

The env is built with the settings stored in the ``env_args`` of the public robomimic v1.5 image datasets:
OSC_POSE (robosuite defaults), control_freq 20, reward_shaping False, ignore_done True, the datasets' cameras
and robots (Transport: two Pandas, ``single-arm-opposed``). Images are flipped the right way up as robomimic
does. ``RobomimicEnv.from_env_args`` / ``from_hdf5`` build the env from a dataset file's own settings instead.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

from jepa_envs.tasks.robosuite_common import (CONSTRUCTION_SEED, RobosuiteTaskEnv, check_action_mode, global_numpy_seed,
                                              osc_pose_config)
from jepa_envs.tasks.spec import TaskSpec, all_task_specs, get_task_spec

ROBOSUITE_ENV_TYPE = 1  # robomimic's EnvType.ROBOSUITE_TYPE, stored as env_args["type"]

# Per-task entries of the robomimic v1.5 image datasets' env_kwargs (the rest is shared, below).
_TASK_KWARGS: dict[str, dict[str, Any]] = {
    "Lift": {"robots": ["Panda"]},
    "PickPlaceCan": {"robots": ["Panda"]},
    "NutAssemblySquare": {"robots": ["Panda"]},
    "ToolHang": {"robots": ["Panda"]},
    "TwoArmTransport": {"robots": ["Panda", "Panda"], "env_configuration": "single-arm-opposed"},
}


def robomimic_env_args(source_task: str, cameras: tuple[str, ...], image_size: int,
                       control_delta: bool = True, task_kwargs: dict | None = None) -> dict:
    """env_args as robomimic stores them in ``data.attrs["env_args"]`` of its image datasets (MimicGen's
    datasets use the same settings); ``task_kwargs`` (robots, ...) default to robomimic's for the task."""
    if task_kwargs is None:
        if source_task not in _TASK_KWARGS:
            raise KeyError(f"no robomimic settings for {source_task!r}; known: {sorted(_TASK_KWARGS)}")
        task_kwargs = _TASK_KWARGS[source_task]
    env_kwargs = {
        "has_renderer": False,
        "has_offscreen_renderer": True,
        "ignore_done": True,
        "use_object_obs": True,
        "use_camera_obs": True,
        "control_freq": 20,
        "controller_configs": osc_pose_config(control_delta),
        "camera_depths": False,
        "camera_heights": image_size,
        "camera_widths": image_size,
        "camera_names": list(cameras),
        "reward_shaping": False,
        **copy.deepcopy(task_kwargs),
    }
    return {"env_name": source_task, "type": ROBOSUITE_ENV_TYPE, "env_kwargs": env_kwargs}


def env_args_from_hdf5(path: str | Path) -> dict:
    """Read ``data.attrs["env_args"]`` (JSON) from a robomimic / MimicGen HDF5 file."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"dataset file {path} does not exist")
    with h5py.File(path, "r") as f:
        if "data" not in f or "env_args" not in f["data"].attrs:
            raise KeyError(f"{path} has no data.attrs['env_args']; is it a robomimic-layout HDF5 file?")
        raw = f["data"].attrs["env_args"]
    try:
        return json.loads(raw)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: data.attrs['env_args'] is not valid JSON ({e})") from e


def _validated_env_args(env_args: dict) -> dict:
    if not isinstance(env_args, dict) or "env_name" not in env_args:
        raise ValueError("env_args must be a dict with 'env_name' and 'env_kwargs' (robomimic's format)")
    if env_args.get("type", ROBOSUITE_ENV_TYPE) != ROBOSUITE_ENV_TYPE:
        raise ValueError(f"env_args type {env_args.get('type')} is not a robosuite env (type 1); "
                         "only robosuite-based datasets can be replayed here")
    ctrl = env_args.get("env_kwargs", {}).get("controller_configs", {})
    if isinstance(ctrl, dict) and "body_parts" in ctrl:
        raise ValueError("env_args come from robosuite >= 1.5 (controller 'body_parts'); this toolkit runs "
                         "robosuite 1.4.1: use the robomimic v1.5 / MimicGen datasets recorded with robosuite 1.4")
    return copy.deepcopy(env_args)


def make_backend_from_env_args(env_args: dict, *, control_delta: bool, use_camera_obs: bool = True,
                               cameras: tuple[str, ...] | None = None, image_size: int | None = None,
                               seed: int = CONSTRUCTION_SEED, **overrides) -> Any:
    """Build the raw robosuite env that a dataset's env_args describe, with our rendering settings; numpy's
    global RNG is seeded with ``seed`` while robosuite builds it (object geometry, masses), then restored."""
    import robosuite

    env_args = _validated_env_args(env_args)
    kwargs = dict(env_args.get("env_kwargs", {}))
    # Our interface decides rendering and the controller's input convention; the rest comes from the file.
    kwargs.update(has_renderer=False, has_offscreen_renderer=use_camera_obs, use_camera_obs=use_camera_obs)
    if use_camera_obs:
        kwargs.update(camera_names=list(cameras or kwargs.get("camera_names", ["agentview"])), camera_depths=False)
        if image_size is not None:
            kwargs.update(camera_heights=image_size, camera_widths=image_size)
    ctrl = kwargs.get("controller_configs") or osc_pose_config(control_delta)
    kwargs["controller_configs"] = {**ctrl, "control_delta": bool(control_delta)}
    kwargs.pop("render_gpu_device_id", None)  # EGL device choice; meaningless under OSMesa
    # robosuite's demonstration files keep env_name inside env_info, and robomimic's convert_robosuite.py copies
    # env_info into env_kwargs as it is (robomimic's data-processing env drops it there too)
    kwargs.pop("env_name", None)
    kwargs.update(overrides)
    _register_source_tasks(env_args["env_name"])
    with global_numpy_seed(seed):
        return robosuite.make(env_args["env_name"], **kwargs)


def _register_source_tasks(env_name: str) -> None:
    """MimicGen's task classes join robosuite's registry only when ``mimicgen`` is imported."""
    from robosuite.environments.base import REGISTERED_ENVS

    if env_name in REGISTERED_ENVS:
        return
    try:
        import mimicgen  # noqa: F401
    except ImportError:
        pass
    if env_name not in REGISTERED_ENVS:
        raise ValueError(f"robosuite has no env {env_name!r}. MimicGen tasks (*_D0, *_D1, ...) need the MimicGen "
                         "source package (see docs/envs_simulation.md); other names must be robosuite 1.4 envs")


def _task_for_env_name(env_name: str, suites: tuple[str, ...]) -> TaskSpec:
    for spec in all_task_specs():
        if spec.suite in suites and spec.source_task == env_name:
            return spec
    raise KeyError(f"no JEPA task uses robosuite env {env_name!r}")


class RobomimicEnv(RobosuiteTaskEnv):
    """Square / ToolHang / Transport with robomimic's PH dataset settings.

    Args:
        task: task name or gym id ("Square", "ToolHang", "Transport").
        image_size: square camera resolution (default the spec's 84).
        render_mode: None or "rgb_array" (``render()`` returns all cameras side by side).
        action_mode: "abs" (paper convention, 10-D per arm) or "delta" (robosuite's native 7-D per arm).
        env_args: robomimic-format env_args to build from instead of the built-in settings.
        hard_reset: robosuite's reset mode; False resets the loaded model instead of rebuilding it.
    """

    SUITES = ("robomimic",)

    def __init__(self, task: str = "Square", image_size: int | None = None, render_mode: str | None = None,
                 action_mode: str = "abs", env_args: dict | None = None, hard_reset: bool = False,
                 reflections: bool | None = None):
        spec = get_task_spec(task)
        if spec.suite not in self.SUITES:
            raise ValueError(f"{type(self).__name__} serves {self.SUITES} tasks; {spec.name} is a {spec.suite} task")
        spec = spec.with_image_size(image_size or spec.image_size)
        if env_args is None:
            env_args = self.default_env_args(spec)
        elif env_args.get("env_name") != spec.source_task:
            raise ValueError(f"env_args are for {env_args.get('env_name')!r} but task {spec.name} runs "
                             f"{spec.source_task!r}")
        self.env_args = _validated_env_args(env_args)
        backend = make_backend_from_env_args(
            self.env_args, control_delta=check_action_mode(action_mode) == "delta",
            cameras=spec.cameras, image_size=spec.image_size, hard_reset=hard_reset)
        # ``reflections``: given, or the recording's own setting (``env_args["render"]``, ours: robomimic ignores
        # it), else robomimic's frames (on)
        if reflections is None:
            reflections = bool(self.env_args.get("render", {}).get("reflections", True))
        super().__init__(spec, backend, render_mode=render_mode, action_mode=action_mode, reflections=reflections)

    @classmethod
    def default_env_args(cls, spec: TaskSpec) -> dict:
        """The settings of the task's public image datasets."""
        return robomimic_env_args(spec.source_task, spec.cameras, spec.image_size)

    @classmethod
    def from_env_args(cls, env_args: dict, **kwargs) -> "RobomimicEnv":
        """Build the task whose robosuite env ``env_args["env_name"]`` names, with the file's settings."""
        spec = _task_for_env_name(_validated_env_args(env_args)["env_name"], cls.SUITES)
        return cls(task=spec.name, env_args=env_args, **kwargs)

    @classmethod
    def from_hdf5(cls, path: str | Path, **kwargs) -> "RobomimicEnv":
        """Build the env described by a dataset file's ``data.attrs["env_args"]``."""
        return cls.from_env_args(env_args_from_hdf5(path), **kwargs)
