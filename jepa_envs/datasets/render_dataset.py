"""``jepa-envs render-dataset``: raw demonstrations (simulator states and actions only) rendered into the image
observations the loader reads, as robomimic's ``dataset_states_to_obs`` does.

Per episode: reset to the recorded model XML (``demo.attrs["model_file"]``) and initial state, then put the
simulator in every recorded state and render the task's cameras (or ``--cameras``) at ``--size``; the low-dim
observations come from the same states. Raw robomimic / MimicGen files (``data.attrs["env_args"]``) and
robosuite's own demonstration files (``data.attrs["env_info"]``, e.g. the Lift demos robosuite ships) are read;
PushT files (states are poses) too. Delta OSC_POSE actions are converted to the paper's absolute convention by
the same state replay as ``convert-abs-actions``, so the output trains as it is.

Reported per episode: ``state_error`` (largest difference between a recorded state and the state the simulator
holds after being put in it: 0 when the recording fits this simulator), ``replay_drift`` (largest difference
between the recorded states and those reached by replaying the recorded actions open-loop from the first one)
and ``replay_success``. A recorded model this robosuite cannot load (other robot geometry, e.g. a file from
another robosuite release) is reported and the task's own model is used with the recorded states, its geoms
resized to the recorded ones of the same name and type (the object a seed drew, e.g. Lift's cube: the states
place it for its own size).

No frame is written unchecked for content: the first and last frame of every episode, every camera, must equal
the live render of the same state by a separately built env of the same model (a renderer whose GL buffers are
lost stays lost, so the last frame vouches for the ones before it); an episode that fails stops the run and
nothing is written.
"""
from __future__ import annotations

import copy
import dataclasses
import gc
import json
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from tqdm import tqdm

from jepa_envs.datasets.convert_abs_actions import delta_to_abs_by_replay
from jepa_envs.datasets.hdf5 import DatasetError, DemoWriter, demo_names, load_dataset, open_hdf5, resolve_task
from jepa_envs.errors import first_line
from jepa_envs.tasks.pusht import PushTEnv
from jepa_envs.tasks.robomimic_env import (ROBOSUITE_ENV_TYPE, make_backend_from_env_args,
                                     robomimic_env_args)
from jepa_envs.tasks.robosuite_common import RobosuiteTaskEnv
from jepa_envs.tasks.spec import TaskSpec

NATIVE_DIM_PER_ARM = 7


def source_env_args(data, path) -> dict:
    """robomimic's env_args of a raw file; robosuite's own ``env_info`` (its demonstration format) becomes
    env_args with robomimic's rendering settings."""
    if "env_args" in data.attrs:
        try:
            return json.loads(data.attrs["env_args"])
        except ValueError as exc:
            raise DatasetError(f"{path}: data.attrs['env_args'] is not valid JSON ({exc})") from None
    if "env_info" in data.attrs:
        info = json.loads(data.attrs["env_info"])
        name = info.pop("env_name", None) or data.attrs.get("env")
        robots = info.pop("robots", "Panda")
        kwargs = {"robots": [robots] if isinstance(robots, str) else list(robots), **info}
        args = robomimic_env_args(name, ("agentview",), 84, control_delta=True, task_kwargs=kwargs)
        args["type"] = ROBOSUITE_ENV_TYPE
        return args
    raise DatasetError(f"{path}: data has neither env_args (robomimic) nor env_info (robosuite); the file does "
                       "not say which environment recorded it")


def recorded_geometry(own_xml: str, recorded_xml: str) -> tuple[str, list[str]]:
    """``own_xml`` with every named geom's ``size`` taken from the geom of the same name and type in
    ``recorded_xml`` where they differ; returns the XML and the names resized. Objects whose size a seed draws
    (Lift's cube) are placed by the recorded states for their recorded size: another size starts the episode
    inside the table or above it."""
    recorded = {}
    for geom in ET.fromstring(recorded_xml).iter("geom"):
        if geom.get("name") and geom.get("size"):
            recorded[geom.get("name")] = (geom.get("type", "sphere"), geom.get("size"))
    root = ET.fromstring(own_xml)
    resized = []
    for geom in root.iter("geom"):
        name, size = geom.get("name"), geom.get("size")
        if name in recorded and size is not None and recorded[name][0] == geom.get("type", "sphere"):
            want = recorded[name][1]
            ours, theirs = [float(v) for v in size.split()], [float(v) for v in want.split()]
            if len(ours) == len(theirs) and ours != theirs:
                geom.set("size", want)
                resized.append(name)
    return ET.tostring(root, encoding="unicode"), resized


def render_dataset(src: str | Path, out: str | Path, task: str | None = None, cameras: tuple[str, ...] = (),
                   size: int | None = None, progress: bool = False, reflections: bool | None = None) -> dict:
    """Render ``src``'s recorded states into ``out`` (robomimic layout with images); returns the report.
    ``reflections``: draw the table's reflection (robomimic's frames) or not (4.5x faster, recorded in the
    output's ``env_args["render"]``); default: the source's own setting, else on."""
    with open_hdf5(src) as f:
        if "data" not in f or not demo_names(f["data"]):
            raise DatasetError(f"{src} holds no data/demo_N episodes")
        data = f["data"]
        names = demo_names(data)
        for name in names:
            for key in ("states", "actions"):
                if key not in data[name]:
                    raise DatasetError(f"{src}: data/{name} has no {key!r}; render-dataset replays recorded simulator "
                                       "states and actions (robomimic's dataset_states_to_obs), so a file without "
                                       "them cannot be rendered: record the states with the demonstrations")
        env_args = source_env_args(data, src)
        if reflections is not None:
            env_args = {**env_args, "render": {**env_args.get("render", {}), "reflections": bool(reflections)}}
        spec = resolve_task(task, env_args, src)
        spec = spec.with_image_size(int(size or spec.image_size))
        if cameras:
            spec = dataclasses.replace(spec, cameras=tuple(cameras))
        if spec.suite == "embedded":
            renderer = PushTRenderer(spec)
        else:   # the recorded actions say the convention (the env_args of some files say delta regardless)
            width = data[names[0]]["actions"].shape[1]
            renderer = RobosuiteRenderer(spec, env_args, delta=width == NATIVE_DIM_PER_ARM * spec.num_arms)
        episodes = []
        try:
            with DemoWriter(out, renderer.output_env_args()) as writer:
                for name in tqdm(names, desc="render-dataset", unit="episode", disable=not progress):
                    demo = data[name]
                    states, actions = demo["states"][()], demo["actions"][()]
                    model = demo.attrs.get("model_file")
                    episode, report = renderer.episode(states, actions, model, name)
                    for key in ("rewards", "dones"):
                        if key in demo:
                            episode[key] = demo[key][()]
                    writer.add(episode, name=name)   # the source's names: its demo_3 stays demo_3
                    episodes.append({"demo": name, "steps": len(actions), **report})
        finally:
            renderer.close()
    return {"task": spec.name, "episodes": episodes, "out": str(out), "cameras": list(spec.cameras),
            "size": spec.image_size, "replay_successes": sum(bool(e["replay_success"]) for e in episodes)}


class PushTRenderer:
    """PushT states are poses (agent xy, block xy, angle): each is set and rendered."""

    def __init__(self, spec: TaskSpec):
        self.spec = spec
        self.env = PushTEnv(image_size=spec.image_size)

    def output_env_args(self) -> dict:
        return {"env_name": "PushT", "type": "jepa_envs", "env_kwargs": {"image_size": self.spec.image_size}}

    def episode(self, states, actions, model, name: str = "demo") -> tuple[dict, dict]:
        obs = []
        error = 0.0
        for state in states:
            o, _ = self.env.reset(options={"state": state})
            obs.append(o)
            error = max(error, float(np.abs(self.env.get_state() - state).max()))
        self.env.reset(options={"state": states[0]})
        drift, success = 0.0, False
        for t, action in enumerate(actions):
            _, _, done, _, info = self.env.step(action)
            success = success or bool(info["is_success"])
            if t + 1 < len(states):
                drift = max(drift, float(np.abs(self.env.get_state() - states[t + 1]).max()))
        episode = {"obs": {k: np.stack([o[k] for o in obs]) for k in obs[0]}, "actions": np.asarray(actions),
                   "states": np.asarray(states)}
        return episode, {"state_error": error, "replay_drift": drift, "replay_success": success}

    def close(self) -> None:
        self.env.close()


class RobosuiteRenderer:
    """robosuite tasks: the recorded model and states, our cameras and low-dim keys, absolute actions."""

    def __init__(self, spec: TaskSpec, env_args: dict, delta: bool):
        self.spec = spec
        self.env_args = copy.deepcopy(env_args)
        self.env_args.setdefault("env_kwargs", {})
        self.delta = delta
        # the recording's render settings (ours, beside robomimic's: the table's reflection off renders 4.5x faster)
        self.render = dict(self.env_args.get("render", {}))
        self.reflections = bool(self.render.get("reflections", True))
        self.env = self._make()
        self.reference: RobosuiteTaskEnv | None = None   # the live renders frames are checked against
        self.own_model: str | None = None   # the task's model with the recorded geom sizes (unusable recording)

    def _make(self):
        # hard_reset=False, as the task's env: robosuite's hard reset rebuilds the model and redraws object sizes
        # (Lift's cube) from the reset seed, so frames and replays would use another cube than the recorded one
        backend = make_backend_from_env_args(self.env_args, control_delta=self.delta, cameras=self.spec.cameras,
                                             image_size=self.spec.image_size, hard_reset=False)
        return RobosuiteTaskEnv(self.spec, backend, action_mode="delta" if self.delta else "abs",
                                reflections=self.reflections)

    def output_env_args(self) -> dict:
        task_kwargs = {k: v for k, v in self.env_args["env_kwargs"].items()
                       if k not in ("camera_names", "camera_heights", "camera_widths", "controller_configs")}
        out = robomimic_env_args(self.env_args["env_name"], self.spec.cameras, self.spec.image_size,
                                 control_delta=False, task_kwargs=task_kwargs)
        ctrl = self.env_args["env_kwargs"].get("controller_configs")
        if isinstance(ctrl, dict):
            out["env_kwargs"]["controller_configs"] = {**ctrl, "control_delta": False}
        if self.render:
            out["render"] = self.render
        return out

    def _reset_to(self, states, model) -> str:
        """Reset to the recorded model and first state; returns which model is used."""
        if model is None:
            self.env.reset(seed=0, options={"state": states[0]})
            return "own"
        try:
            self.env.reset(seed=0, options={"model": model, "state": states[0]})
            return "recorded"
        except Exception as exc:   # another robosuite's geometry: rebuild ours, keep the states
            why = first_line(str(exc), 120)
        # Out of the except block on purpose: its traceback held the render context robosuite made for the
        # recorded model, and that context, freed later with ours current, deleted our GL buffers by id (every
        # frame black or noise). Free it now, with it current.
        self.env.close()
        gc.collect()
        self.env = self._make()
        own, resized = recorded_geometry(self.env.backend.sim.model.get_xml(), model)
        self.own_model = own if resized else None
        self.env.reset(seed=0, options={"state": states[0]} if not resized else {"model": own, "state": states[0]})
        sized = f"; {len(resized)} geoms sized as recorded: {', '.join(resized[:4])}" if resized else ""
        return f"own (recorded XML unusable here: {why}{sized})"

    def check_frames(self, name: str, obs: dict, states, model, which: str) -> None:
        """Raise unless the first and last frame of each camera equal the live render of their state by a
        separately built env of the same model (see the module docstring)."""
        if self.reference is None:
            self.reference = self._make()
        drawn = model if which == "recorded" else self.own_model
        self.reference.reset(seed=0, options={"state": states[0]} if drawn is None
                             else {"model": drawn, "state": states[0]})
        for t in sorted({0, len(states) - 1}):
            self.reference.set_sim_state(states[t])
            live = self.reference.observe_now()
            for key in self.spec.image_keys:
                if not np.array_equal(obs[key][t], live[key]):
                    diff = np.abs(obs[key][t].astype(int) - live[key]).max()
                    raise DatasetError(f"data/{name}: frame {t} of {key} is not the live render of its state "
                                       f"(largest pixel difference {diff}; the renderer lost its GL buffers or "
                                       f"renders another scene); nothing was written. Re-run; if it recurs, "
                                       f"report it with MUJOCO_GL={os.environ.get('MUJOCO_GL', '<unset>')}")

    def episode(self, states, actions, model, name: str = "demo") -> tuple[dict, dict]:
        states = np.asarray(states, np.float64)
        actions = np.asarray(actions, np.float64)
        which = self._reset_to(states, model)
        sim = self.env.backend.sim
        obs, error = [], 0.0
        for state in states:
            self.env.set_sim_state(state)
            error = max(error, float(np.abs(sim.get_state().flatten() - state).max()))
            obs.append(self.env.observe_now())
        obs = {k: np.stack([o[k] for o in obs]) for k in obs[0]}
        self.check_frames(name, obs, states, model, which)
        # open-loop replay of the recorded actions from the first state
        self.env.set_sim_state(states[0])
        drift, success = 0.0, False
        for t, action in enumerate(actions):
            _, _, done, _, info = self.env.step(action)
            success = success or bool(info["is_success"])
            if t + 1 < len(states):   # the first entry is MuJoCo's clock, which a replay restarts
                drift = max(drift, float(np.abs(sim.get_state().flatten()[1:] - states[t + 1][1:]).max()))
        if self.delta:   # set from the recorded actions' width (render_dataset)
            actions = delta_to_abs_by_replay(self.env.backend, states, actions)
        episode = {"obs": obs, "actions": actions.astype(np.float32), "states": states}
        return episode, {"model": which, "state_error": error, "replay_drift": drift, "replay_success": success}

    def close(self) -> None:
        self.env.close()
        if self.reference is not None:
            self.reference.close()


def replay_in_env(path: str | Path, task: str, episodes: int | None = None) -> dict:
    """Replay a rendered file's actions open-loop in ``gym.make(<task's id>)`` from each episode's recorded first
    state, the actions read through the training loader (``load_dataset``); counts the episodes that succeed."""
    import gymnasium as gym

    demos = load_dataset(path, task=task, cache_dir=False)
    spec = demos.spec
    with open_hdf5(path) as f:
        first_states = [f["data"][n]["states"][0] for n in demos.demo_names]
    longest = int(np.diff(demos.episode_ends, prepend=0).max())
    # a replay runs the recording's own length (human demonstrations may outlast the evaluation time limit), and
    # renders nothing: success is read from the simulator
    env = gym.make(spec.env_id, image_size=spec.image_size, max_episode_steps=max(longest, spec.max_episode_steps))
    env.unwrapped.set_render_images(False)
    results = []
    try:
        for i in range(min(demos.num_episodes(), episodes or demos.num_episodes())):
            env.reset(seed=i, options={"state": first_states[i]})
            steps = demos.actions[demos.episode_slice(i)]
            success_step = None
            for t, action in enumerate(steps):
                *_, terminated, truncated, info = env.step(action)
                if info["is_success"]:
                    success_step = t + 1
                    break
            results.append({"demo": demos.demo_names[i], "steps": len(steps), "success": success_step is not None,
                            "success_step": success_step,
                            "within_time_limit": success_step is not None and success_step <= spec.max_episode_steps})
    finally:
        env.close()
    return {"task": spec.name, "episodes": results, "successes": sum(r["success"] for r in results)}
