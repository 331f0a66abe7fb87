"""robomimic's side of `make interop`'s robomimic check, run by scripts/interop_robomimic.py in robomimic's own venv
(robomimic 0.3.0, robosuite 1.4.1, mujoco 3.3.7; scripts/interop.sh builds it). Imports nothing of this project.

    python interop_robomimic_peer.py replay|observe IN.npz OUT.npz

IN.npz: ``env_meta`` (robomimic's env_args JSON), ``model`` (MJCF XML), ``states`` (T, D) or (1, D), ``actions``
(T, 7: robosuite's delta OSC_POSE input), ``cameras`` (names; empty for none) and ``size``. With a single state the
actions are first stepped open-loop from it in robomimic's ``EnvRobosuite`` (a rollout that yields the states).
Then, as ``dataset_states_to_obs.py`` does, for every t: ``reset_to({"states": states[t]})`` gives ``obs/<key>``;
``step(actions[t])`` gives the observation robomimic's step returns (``step_obs/<key>``), what ``get_observation()``
says after it (``after_obs/<key>``), the state it reached (``next_states``) and the goal robosuite's
OSC controller derived from the delta action (``goal_pos``, ``goal_ori``), beside the end-effector position the
controller held before that step and whether it re-reads the arm first (``controller_pos``, ``controller_fresh``).
``observe`` gives only
``obs/<key>`` of each of ``states``. Each prints one JSON line.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np


def make_env(env_meta: dict, cameras: list[str], size: int):
    """The env robomimic's dataset_states_to_obs.py builds (no camera, no offscreen renderer, when ``cameras`` is
    empty). Its other constructor, ``create_env_from_metadata``, would refuse the env_args its own
    convert_robosuite.py writes (env_kwargs holding env_name)."""
    import robomimic.utils.env_utils as EnvUtils

    return EnvUtils.create_env_for_data_processing(env_meta=env_meta, camera_names=cameras, camera_height=size,
                                                   camera_width=size, reward_shaping=False)


def sim_state(env) -> np.ndarray:
    """robomimic's ``get_state()["states"]`` without the model XML it also serialises."""
    return np.array(env.env.sim.get_state().flatten())


def stack(frames: list[dict], prefix: str) -> dict:
    return {f"{prefix}/{k}": np.stack([np.asarray(f[k]) for f in frames]) for k in frames[0]}


def replay(src: str, dst: str) -> dict:
    import robomimic
    import robosuite

    data = np.load(src)
    env_meta = json.loads(str(data["env_meta"]))
    cameras = [str(c) for c in data["cameras"]]
    states, actions = np.asarray(data["states"], np.float64), np.asarray(data["actions"], np.float64)
    env = make_env(env_meta, cameras, int(data["size"]))
    env.reset()
    env.reset_to({"model": str(data["model"]), "states": states[0]})
    started = time.perf_counter()
    if len(states) == 1:   # a rollout: robomimic's env steps the actions from the one state given
        rolled = [states[0]]
        for action in actions[:-1]:
            env.step(action)
            rolled.append(sim_state(env))
        states = np.stack(rolled)
        # the replay below starts as the rollout did (a reset to the model also resets the grippers' commands)
        env.reset_to({"model": str(data["model"]), "states": states[0]})
    out = {"states": states}
    frames = {"obs": [], "step_obs": [], "after_obs": []}
    next_states, goal_pos, goal_ori, controller_pos, controller_fresh = [], [], [], [], []
    robot = env.env.robots[0]
    for state, action in zip(states, actions):
        frames["obs"].append(env.reset_to({"states": state}))
        # the pose the controller adds the delta to: robosuite re-reads the arm (new_update) only once the controller
        # has run since it last read it; otherwise the pose it holds
        controller_pos.append(np.array(robot.controller.ee_pos))
        controller_fresh.append(bool(robot.controller.new_update))
        frames["step_obs"].append(env.step(action)[0])
        next_states.append(sim_state(env))
        goal_pos.append(np.array(robot.controller.goal_pos))
        goal_ori.append(np.array(robot.controller.goal_ori))
        if cameras:
            frames["after_obs"].append(env.get_observation())
    out.update(next_states=np.stack(next_states), goal_pos=np.stack(goal_pos), goal_ori=np.stack(goal_ori),
               controller_pos=np.stack(controller_pos), controller_fresh=np.array(controller_fresh),
               delta_scale=robot.controller.scale_action(np.ones(6))[:3])
    for prefix, seen in frames.items():
        if seen:
            out.update(stack(seen, prefix))
    np.savez(dst, **out)
    return {"robomimic": robomimic.__version__, "robosuite": robosuite.__version__,
            "mujoco": __import__("mujoco").__version__, "env": type(env).__name__, "steps": len(actions),
            "seconds": round(time.perf_counter() - started, 1)}


def observe(src: str, dst: str) -> dict:
    """``obs/<key>`` of each of ``states`` (after a reset to ``model``), as dataset_states_to_obs.py records them."""
    data = np.load(src)
    env = make_env(json.loads(str(data["env_meta"])), [str(c) for c in data["cameras"]], int(data["size"]))
    states = np.asarray(data["states"], np.float64)
    env.reset()
    env.reset_to({"model": str(data["model"]), "states": states[0]})
    started = time.perf_counter()
    np.savez(dst, **stack([env.reset_to({"states": state}) for state in states], "obs"))
    return {"states": len(states), "seconds": round(time.perf_counter() - started, 1)}


if __name__ == "__main__":
    commands = {"replay": replay, "observe": observe}
    if len(sys.argv) != 4 or sys.argv[1] not in commands:
        sys.exit("usage: interop_robomimic_peer.py replay|observe IN.npz OUT.npz")
    print(json.dumps(commands[sys.argv[1]](sys.argv[2], sys.argv[3])))
