"""``jepa-envs convert-abs-actions``: datasets recorded with delta actions, converted to absolute ones.

robomimic and MimicGen record delta OSC_POSE actions. They are converted by replaying the recorded states: at
every step the simulator is put in the recorded state, the delta action is handed to each arm's controller, and
the goal pose the controller derives from it is the absolute action (``abs_actions``) that produces the same
motion.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from jepa_envs.tasks import rotations
from jepa_envs.tasks.abs_actions import ABS_DIM_PER_ARM, NATIVE_DIM_PER_ARM, split_arms
from jepa_envs.tasks.robomimic_env import env_args_from_hdf5, make_backend_from_env_args


def delta_to_abs_by_replay(backend, states: np.ndarray, delta_actions: np.ndarray) -> np.ndarray:
    """Absolute actions (T, 10 * arms) equivalent to recorded delta actions (T, 7 * arms).

    ``backend`` is a robosuite env built with delta OSC_POSE controllers and the dataset's settings;
    ``states[t]`` is MuJoCo's flattened state before action t (the robomimic ``states`` dataset).
    """
    robots = backend.robots
    num_arms = len(robots)
    states = np.asarray(states, dtype=np.float64)
    deltas = split_arms(delta_actions, num_arms, NATIVE_DIM_PER_ARM, "delta")
    if deltas.ndim != 3 or len(states) != len(deltas):
        raise ValueError(f"need one state per action: got {len(states)} states and actions of shape "
                         f"{np.shape(delta_actions)}")
    expected = backend.sim.get_state().flatten().shape[0]
    if states.shape[1] != expected:
        raise ValueError(f"dataset states have {states.shape[1]} values but this env's MuJoCo state has "
                         f"{expected}; the dataset was recorded with a different env (check env_args)")
    for robot in robots:
        if not robot.controller.use_delta:
            raise ValueError("delta_to_abs_by_replay needs the delta controller (control_delta=True)")
    out = np.empty((len(deltas), num_arms, ABS_DIM_PER_ARM))
    for t, (state, step_deltas) in enumerate(zip(states, deltas)):
        backend.sim.set_state_from_flattened(state)
        backend.sim.forward()
        for i, (robot, delta) in enumerate(zip(robots, step_deltas)):
            ctrl = robot.controller
            ctrl.update(force=True)
            if t == 0:
                # a freshly reset controller holds its current orientation; a zero rotation delta keeps the goal
                ctrl.goal_ori = np.array(ctrl.ee_ori_mat)
            ctrl.set_goal(delta[:6])
            out[t, i] = np.concatenate([ctrl.goal_pos, rotations.matrix_to_rot6d(ctrl.goal_ori), delta[6:7]])
    return out.reshape(len(deltas), num_arms * ABS_DIM_PER_ARM)


def convert_abs_actions(in_path: str | Path, out_path: str | Path, progress: bool = True) -> Path:
    """Copy a robomimic/MimicGen HDF5 file, replacing each demo's delta ``actions`` by absolute ones.

    In the copy: ``data/demo_N/actions`` holds our absolute actions (10-D per arm), ``actions_delta`` the
    original ones; ``data.attrs["env_args"]`` records ``control_delta: false`` and
    ``data.attrs["action_convention"] = "abs_pos_rot6d_gripper"``.
    """
    in_path, out_path = Path(in_path), Path(out_path)
    if not in_path.is_file():
        raise FileNotFoundError(f"input dataset {in_path} does not exist")
    if in_path.resolve() == out_path.resolve():
        raise ValueError("output path must differ from the input path; the input is left untouched")
    env_args = env_args_from_hdf5(in_path)
    with h5py.File(in_path, "r") as f:
        if f["data"].attrs.get("action_convention") == "abs_pos_rot6d_gripper":
            raise ValueError(f"{in_path} already holds absolute actions")
    backend = make_backend_from_env_args(env_args, control_delta=True, use_camera_obs=False)
    tmp = out_path.with_name(out_path.name + ".partial")
    shutil.copyfile(in_path, tmp)
    try:
        with h5py.File(tmp, "r+") as f:
            data = f["data"]
            demos = sorted((k for k in data if k.startswith("demo")), key=lambda k: int(k.split("_")[-1]))
            for name in tqdm(demos, desc="convert-abs-actions", disable=not progress):
                demo = data[name]
                for key in ("states", "actions"):
                    if key not in demo:
                        raise KeyError(f"{in_path}: data/{name} has no {key!r} dataset; "
                                       "absolute conversion needs recorded states and actions")
                abs_act = delta_to_abs_by_replay(backend, demo["states"][()], demo["actions"][()])
                demo.move("actions", "actions_delta")
                demo.create_dataset("actions", data=abs_act.astype(np.float32))
            env_args["env_kwargs"] = dict(env_args.get("env_kwargs", {}))
            ctrl = env_args["env_kwargs"].get("controller_configs")
            if isinstance(ctrl, dict):
                env_args["env_kwargs"]["controller_configs"] = {**ctrl, "control_delta": False}
            data.attrs["env_args"] = json.dumps(env_args)
            data.attrs["action_convention"] = "abs_pos_rot6d_gripper"
        tmp.replace(out_path)
    finally:
        backend.close()
        tmp.unlink(missing_ok=True)
    return out_path
