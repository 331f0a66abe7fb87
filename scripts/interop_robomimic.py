"""`make interop`, robomimic part: our robomimic tasks checked against robomimic 0.3.0 itself (its ``EnvRobosuite``,
its ``dataset_states_to_obs.py``, its replay of delta actions), run in robomimic's own venv (scripts/interop.sh
builds it; robosuite 1.4.1 and mujoco 3.3.7 there as here) through scripts/interop_robomimic_peer.py.

1. Observations. For Lift, Can and Square our env (``gym.make("JEPA/<task>-v0")``) is reset with seed 0; robomimic's
   ``EnvRobosuite``, built as ``dataset_states_to_obs.py`` builds it from the task's env_args (same cameras, same
   image size), is reset to our model XML and state and steps ``--steps`` smooth random delta actions. Every state it
   passes through is then put into both envs: each observation key is compared (images exactly, low-dim to 1e-6).
2. Datasets. robosuite's shipped human Lift demonstrations, converted by robomimic's own ``convert_robosuite.py``,
   rendered by our ``jepa-envs render-dataset`` and by robomimic's ``dataset_states_to_obs.py`` (same cameras and
   size): every array both write is compared. robosuite 1.4.1 cannot load the robot of the model XML recorded with
   1.4.0, in robomimic as in ours (recorded and reported); robomimic renders a copy whose XML is the model our
   render-dataset falls back to (the task's, with the recorded geom sizes).
3. Actions. Our delta -> absolute conversion (``delta_to_abs_by_replay``) of the same delta actions, against the
   goal robosuite's controller derives inside robomimic's replay (reset to each state, step the delta action), and
   our absolute actions stepped from each state in our env against the state robomimic's replay reaches: on the
   random rollouts of (1) and on the three human Lift demonstrations (the actions our render-dataset wrote).

    python scripts/interop_robomimic.py --robomimic-python .cache/interop/robomimic/bin/python \\
        [--steps 20] [--demos 3] [--demo-steps N] [--tasks Lift Can Square] [--table docs/robomimic_parity.md]

Prints one table, writes interop_out/robomimic.json (with its wall time and the run id scripts/interop.sh gives,
``INTEROP_RUN_ID``) and optionally the markdown table. Exit 1 when a check fails.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "scripts" / "interop_robomimic_peer.py"
TASKS = ("Lift", "Can", "Square")
SIZE = 84
LOWDIM_TOL = 1e-6      # ours are float32: robosuite's float64 values (|x| < 2) rounded, at most 1.2e-7 off
GOAL_TOL = 1e-9        # metres between our absolute action and robosuite's own goal
# radians: robosuite's quat2mat rounds the quaternion to float32, so its goal matrices are orthonormal to ~1e-8 only,
# and a 6-D rotation (two columns, re-orthonormalised) stands for the nearest rotation
GOAL_ORI_TOL = 1e-6
STATE_TOL = 1e-6       # one step from the same state, our absolute action against robomimic's delta action
CAMERAS = ("agentview", "robot0_eye_in_hand")


def run(cmd: list[str], what: str) -> str:
    out = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{what} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return out.stdout.strip().splitlines()[-1] if out.stdout.strip() else ""


def peer(command: str, py: str, work: Path, name: str, env_meta: dict, model: str, states: np.ndarray,
         actions: np.ndarray, cameras: tuple[str, ...]) -> tuple[dict, dict]:
    src, dst = work / f"{name}-{command}-in.npz", work / f"{name}-{command}-out.npz"
    np.savez(src, env_meta=json.dumps(env_meta), model=model, states=states, actions=actions,
             cameras=np.array(cameras, dtype=str), size=SIZE)
    info = json.loads(run([py, PEER, command, src, dst], f"robomimic {command} ({name})"))
    with np.load(dst) as z:
        return info, {k: z[k] for k in z.files}


def smooth_deltas(seed: int, steps: int) -> np.ndarray:
    """Delta OSC_POSE actions (steps, 7): a smoothed random walk in [-1, 1], gripper open then closed."""
    rng = np.random.default_rng(seed)
    actions, a = np.zeros((steps, 7)), np.zeros(6)
    for t in range(steps):
        a = 0.7 * a + 0.3 * rng.uniform(-1, 1, 6)
        actions[t, :6] = a
        actions[t, 6] = -1.0 if t < steps // 2 else 1.0
    return actions


def key_diff(ours: np.ndarray, theirs: np.ndarray) -> dict:
    """Images: exact equality and the largest pixel difference. Low-dim: the largest difference from robomimic's
    float64 values and whether ours are exactly those values rounded to float32."""
    if ours.shape != theirs.shape:
        return {"shape": [list(ours.shape), list(theirs.shape)], "max": None, "ok": False}
    if ours.dtype == np.uint8:
        equal = bool(np.array_equal(ours, theirs))
        return {"kind": "image", "max": int(np.abs(ours.astype(int) - theirs.astype(int)).max()), "equal": equal,
                "ok": equal}
    diff = float(np.abs(ours.astype(np.float64) - theirs.astype(np.float64)).max())
    return {"kind": "low-dim", "max": diff, "dtypes": [str(ours.dtype), str(theirs.dtype)],
            "float32_of_theirs": bool(np.array_equal(ours, theirs.astype(ours.dtype))), "ok": diff <= LOWDIM_TOL}


def compare_obs(ours: dict, theirs: dict, prefix: str, keys) -> dict:
    return {k: key_diff(np.asarray(ours[k]), theirs[f"{prefix}/{k}"]) for k in keys}


def goal_diff(absolute: np.ndarray, goal_pos: np.ndarray, goal_ori: np.ndarray) -> dict:
    """Largest position difference and rotation angle between our absolute actions and robosuite's goals. The
    angle is taken from the chord, |R1 - R2|_F = 2 sqrt(2) sin(angle / 2): arccos of the trace cannot resolve
    angles below ~1e-8 rad."""
    from jepa_envs.tasks.rotations import rot6d_to_matrix

    pos = float(np.abs(absolute[:, :3] - goal_pos).max())
    chord = np.linalg.norm(rot6d_to_matrix(absolute[:, 3:9].astype(np.float64)) - goal_ori, axis=(1, 2))
    ori = float((2 * np.arcsin(np.minimum(1.0, chord / (2 * np.sqrt(2))))).max())
    return {"position_max_m": pos, "orientation_max_rad": ori}


def first_rotation_step(deltas: np.ndarray) -> int:
    """The first step whose rotation delta robosuite does not take for zero (``math.isclose(v, 0.0)`` on each
    scaled component, as its OSC ``set_goal``; the scaling maps 0 to 0): until then it keeps its goal orientation."""
    moved = [any(not math.isclose(v, 0.0) for v in row) for row in np.clip(deltas[:, 3:6], -1, 1)]
    return moved.index(True) if any(moved) else len(moved)


def action_diff(absolute: np.ndarray, rm: dict, deltas: np.ndarray) -> dict:
    """Our absolute actions against the goals robosuite set inside robomimic's replay, step 0 apart: robosuite adds a
    delta to the end-effector pose its controller reads from the arm, but re-reads the arm only once the controller
    has run since its last read. After ``reset_to`` set the first state it has not (it last read the arm at the
    reset before), so step 0's delta goes to the reset's pose; our conversion, like the recording, starts from the
    pose of the state. Checked: robosuite's goal = the pose it used + the scaled delta at every step, it re-read the
    arm at every step from step 1 on, and step 0's difference is the distance between the two poses. robosuite
    keeps its goal orientation while the rotation delta is zero, so step 0's orientation carries over until the
    first non-zero one (human demonstrations often rotate late): those steps are compared with step 0's."""
    fresh = rm["controller_fresh"].astype(bool)
    used = np.where(fresh[:, None], rm["obs/robot0_eef_pos"], rm["controller_pos"])
    rule = used + rm["delta_scale"] * np.clip(deltas[:, :3], -1, 1)
    behind = float(np.abs(rm["controller_pos"][0] - rm["obs/robot0_eef_pos"][0]).max())
    first = goal_diff(absolute[:1], rm["goal_pos"][:1], rm["goal_ori"][:1])
    k = max(1, first_rotation_step(deltas))
    later = goal_diff(absolute[1:], rm["goal_pos"][1:], rm["goal_ori"][1:])
    if k < len(absolute):
        later["orientation_max_rad"] = goal_diff(absolute[k:], rm["goal_pos"][k:], rm["goal_ori"][k:])[
            "orientation_max_rad"]
    else:   # no rotation delta at all: every orientation is step 0's, compared below
        later["orientation_max_rad"] = None
    carried = [goal_diff(absolute[t:t + 1], rm["goal_pos"][t:t + 1], rm["goal_ori"][t:t + 1])["orientation_max_rad"]
               for t in range(1, k)]
    gram = np.einsum("nij,nkj->nik", rm["goal_ori"], rm["goal_ori"])
    return {"later": later, "first": first, "orientation_from_step": k,
            "orientation_carried_max_rad": max(carried, default=0.0),
            "orientation_carried_is_step0s": all(abs(c - first["orientation_max_rad"]) <= GOAL_ORI_TOL
                                                 for c in carried),
            "robosuite_goal_not_orthonormal_by": float(np.abs(gram - np.eye(3)).max()),
            "robosuite_goal_rule_max_m": float(np.abs(rm["goal_pos"] - rule).max()),
            "controller_reread_first": bool(fresh[0]), "controller_reread_later": bool(fresh[1:].all()),
            "controller_pose_behind_first_m": behind,
            "first_explained": bool(fresh[0] or abs(first["position_max_m"] - behind) <= 1e-6)}


def action_ok(a: dict) -> bool:
    ori = a["later"]["orientation_max_rad"]
    return (a["later"]["position_max_m"] <= GOAL_TOL and (ori is None or ori <= GOAL_ORI_TOL)
            and a["robosuite_goal_rule_max_m"] <= GOAL_TOL and a["controller_reread_later"] and a["first_explained"]
            and a["orientation_carried_is_step0s"])


def stack(frames: list[dict]) -> dict:
    return {k: np.stack([f[k] for f in frames]) for k in frames[0]}


def replay_ours(env, model: str, states: np.ndarray, absolute: np.ndarray) -> tuple[np.ndarray, list[dict]]:
    """Our absolute actions stepped from each recorded state in sequence (robomimic's replay does the same with
    the delta ones): the states reached and our step observations."""
    env.reset(seed=0, options={"model": model, "state": states[0]})
    reached, observed = [], []
    for state, action in zip(states, absolute):
        env.set_sim_state(state)
        observed.append(env.step(action)[0])
        reached.append(env.backend.sim.get_state().flatten())
    return np.stack(reached), observed


def check_task(task: str, py: str, work: Path, steps: int) -> dict:
    """(1) and (3) for one task on a robomimic rollout of smooth random delta actions."""
    import gymnasium as gym

    import jepa_envs  # noqa: F401  registers the ids
    from jepa_envs.datasets.convert_abs_actions import delta_to_abs_by_replay
    from jepa_envs.tasks.robomimic_env import RobomimicEnv, robomimic_env_args
    from jepa_envs.tasks.spec import get_task_spec

    spec = get_task_spec(task).with_image_size(SIZE)
    keys = (*spec.image_keys, *spec.lowdim_keys)
    env = gym.make(spec.env_id, image_size=SIZE).unwrapped
    delta_env = RobomimicEnv(task, image_size=SIZE, action_mode="delta")
    try:
        env.reset(seed=0)
        model = env.backend.sim.model.get_xml()
        start = env.backend.sim.get_state().flatten()
        env_meta = robomimic_env_args(spec.source_task, spec.cameras, SIZE)   # robomimic's datasets: delta control
        deltas = smooth_deltas(seed=len(task), steps=steps)
        info, rm = peer("replay", py, work, task, env_meta, model, start[None], deltas, spec.cameras)
        states = rm["states"]
        started = time.perf_counter()
        # 1. the observation of each state
        env.reset(seed=0, options={"model": model, "state": states[0]})
        ours = []
        for state in states:
            env.set_sim_state(state)
            ours.append(env.observe_now())
        result = {"robomimic": info, "states": len(states), "keys": list(keys),
                  "obs": compare_obs(stack(ours), rm, "obs", keys),
                  "robomimic_only": sorted(k[4:] for k in rm if k.startswith("obs/") and k[4:] not in keys)}
        # 3. delta -> absolute, then stepped from each state
        delta_env.set_render_images(False)
        delta_env.reset(seed=0, options={"model": model, "state": states[0]})
        absolute = delta_to_abs_by_replay(delta_env.backend, states, deltas)
        reached, stepped = replay_ours(env, model, states, absolute)
        step_obs = stack(stepped)
        gap = np.abs(reached - rm["next_states"]).max(axis=1)
        result["actions"] = {
            **action_diff(absolute, rm, deltas), "state_first": float(gap[0]), "state_later": float(gap[1:].max()),
            # robomimic's own rollout against its own replay from each state
            "robomimic_rollout_vs_replay_max": float(np.abs(rm["next_states"][1:-1] - states[2:]).max())}
        # robomimic's observation of the states our steps reached (step 0 apart: its goal differs, above)
        _, seen = peer("observe", py, work, task, env_meta, model, reached[1:], deltas[1:], spec.cameras)
        later = {k: v[1:] for k, v in step_obs.items()}
        theirs = {k: v[1:] for k, v in rm.items() if k.split("/")[0] in ("after_obs", "step_obs")}
        result["step_obs"] = {"vs_next_state_obs": compare_obs(later, seen, "obs", keys),
                              "vs_robomimic_after_step": compare_obs(later, theirs, "after_obs", keys),
                              "vs_robomimic_step_return": compare_obs(later, theirs, "step_obs", keys)}
        result["ours_seconds"] = round(time.perf_counter() - started, 1)
    finally:
        env.close()
        delta_env.close()
    a = result["actions"]
    result["ok"] = (all(r["ok"] for r in result["obs"].values())
                    and all(r["ok"] for r in result["step_obs"]["vs_next_state_obs"].values())
                    and action_ok(a) and a["state_later"] <= STATE_TOL)
    return result


def refit_model_file(src: Path, dst: Path) -> list[str]:
    """A copy of robosuite's Lift demonstrations whose model XML this robosuite can load: the task's model with
    the recorded geom sizes, the very model `render-dataset` falls back to (robosuite 1.4.0's robot geometry
    fails to load in 1.4.1, in robomimic as in ours). Returns the geoms resized."""
    from jepa_envs.datasets.render_dataset import recorded_geometry, source_env_args
    from jepa_envs.tasks.robomimic_env import make_backend_from_env_args

    shutil.copyfile(src, dst)
    with h5py.File(dst, "r+") as f:
        env_args = source_env_args(f["data"], dst)
        backend = make_backend_from_env_args(env_args, control_delta=True, cameras=CAMERAS, image_size=SIZE,
                                             hard_reset=False)
        own = backend.sim.model.get_xml()
        backend.close()
        resized = set()
        for name in f["data"]:
            if isinstance(f["data"][name], h5py.Group) and "model_file" in f["data"][name].attrs:
                xml, names = recorded_geometry(own, f["data"][name].attrs["model_file"])
                f["data"][name].attrs["model_file"] = xml
                resized.update(names)
    return sorted(resized)


def render_ours(raw: Path, out: Path) -> dict:
    line = run([sys.executable, "-m", "jepa_envs.cli", "render-dataset", raw, out, "--task", "Lift",
                "--size", str(SIZE), "--no-progress"], f"jepa-envs render-dataset {raw.name}")
    return json.loads(line)


def render_robomimic(py: str, raw: Path, name: str) -> subprocess.CompletedProcess:
    return subprocess.run([py, "-m", "robomimic.scripts.dataset_states_to_obs", "--dataset", str(raw),
                           "--output_name", name, "--done_mode", "2", "--camera_names", *CAMERAS,
                           "--camera_height", str(SIZE), "--camera_width", str(SIZE)],
                          capture_output=True, text=True)


def compare_files(ours: Path, theirs: Path) -> dict:
    """Every array both files hold, demo by demo, pooled over demos; the keys only one writes."""
    from jepa_envs.datasets.hdf5 import demo_names

    rows: dict[str, dict] = {}
    with h5py.File(ours) as a, h5py.File(theirs) as b:
        names = demo_names(a["data"])
        if names != demo_names(b["data"]):
            return {"ok": False, "demos": [names, demo_names(b["data"])]}
        ours_keys = {k for k in a["data"][names[0]].keys() if k != "obs"} | {
            f"obs/{k}" for k in a["data"][names[0]]["obs"]}
        theirs_keys = {k for k in b["data"][names[0]].keys() if k not in ("obs", "next_obs")} | {
            f"obs/{k}" for k in b["data"][names[0]]["obs"]}
        for key in sorted(ours_keys & theirs_keys - {"actions"}):   # actions: ours absolute, theirs delta
            diffs = [key_diff(a["data"][n][key][()], b["data"][n][key][()]) for n in names]
            rows[key] = {"max": max(d["max"] for d in diffs) if all(d["max"] is not None for d in diffs) else None,
                         "ok": all(d["ok"] for d in diffs), "frames": int(sum(len(a["data"][n][key]) for n in names))}
            if key == "states":   # identical copies of the recorded states, not observations
                rows[key]["ok"] = rows[key]["max"] == 0
        return {"keys": rows, "ours_only": sorted(ours_keys - theirs_keys),
                "robomimic_only": sorted(theirs_keys - ours_keys) + ["next_obs/*"], "demos": names,
                "ok": all(r["ok"] for r in rows.values())}


def human_actions(py: str, work: Path, refit: Path, ours: Path) -> list[dict]:
    """(3) on robosuite's human Lift demonstrations: robomimic replays each recorded delta action from its recorded
    state in the refit model; our conversion of the same actions (float64) and the absolute actions `render-dataset`
    wrote to ``ours`` (float32) are compared with robosuite's goals, and the latter stepped from each state."""
    from jepa_envs.datasets.convert_abs_actions import delta_to_abs_by_replay
    from jepa_envs.datasets.hdf5 import demo_names
    from jepa_envs.tasks.robomimic_env import RobomimicEnv, env_args_from_hdf5

    env_args = env_args_from_hdf5(refit)
    env = RobomimicEnv.from_env_args(env_args, image_size=SIZE)
    delta_env = RobomimicEnv.from_env_args(env_args, image_size=SIZE, action_mode="delta")
    env.set_render_images(False)
    delta_env.set_render_images(False)
    rows = []
    try:
        with h5py.File(refit) as f, h5py.File(ours) as o:
            for name in demo_names(f["data"]):
                model = f["data"][name].attrs["model_file"]
                states, deltas = f["data"][name]["states"][()], f["data"][name]["actions"][()]
                info, rm = peer("replay", py, work, f"lift-{name}", env_args, model, states, deltas, ())
                delta_env.reset(seed=0, options={"model": model, "state": states[0]})
                converted = delta_to_abs_by_replay(delta_env.backend, states, deltas)
                written = o["data"][name]["actions"][()]
                reached, _ = replay_ours(env, model, states, written)
                gap = np.abs(reached - rm["next_states"]).max(axis=1)
                k = max(1, first_rotation_step(deltas))   # before it, the goals' orientations differ (above)
                rows.append({"demo": name, "steps": len(states), "robomimic": info,
                             "converted": action_diff(converted, rm, deltas),
                             "written_float32": action_diff(written, rm, deltas),
                             "state_first": float(gap[0]), "state_before_rotation": float(gap[1:k].max(initial=0)),
                             "state_from_rotation": float(gap[k:].max(initial=0))})
    finally:
        env.close()
        delta_env.close()
    return rows


def check_datasets(py: str, work: Path, demos: int, steps: int | None = None) -> dict:
    """(2) and the human-demonstration half of (3)."""
    from jepa_envs.datasets.hdf5 import demo_names
    from jepa_policy.demo.pick import human_demos_file

    raw = work / "lift_demo.hdf5"   # robosuite's file, its first `demos` demonstrations (their first `steps` steps)
    with h5py.File(human_demos_file()) as f, h5py.File(raw, "w") as g:
        data = g.create_group("data")
        for key, value in f["data"].attrs.items():
            data.attrs[key] = value
        for name in demo_names(f["data"])[:demos]:
            demo = data.create_group(name)
            demo.attrs["model_file"] = f["data"][name].attrs["model_file"]
            for key in ("states", "actions"):
                demo.create_dataset(key, data=f["data"][name][key][:steps])
    run([py, "-m", "robomimic.scripts.conversion.convert_robosuite", "--dataset", raw], "robomimic convert_robosuite")
    result = {"source": str(human_demos_file()), "demos": demos, "steps_per_demo": steps}
    # robomimic on the file as recorded
    started = time.perf_counter()
    as_recorded = render_robomimic(py, raw, "robomimic_as_recorded.hdf5")
    result["robomimic_as_recorded"] = {
        "returncode": as_recorded.returncode,
        "error": (as_recorded.stderr.strip().splitlines() or [""])[-1][:160]}
    refit = work / "lift_demo_refit.hdf5"
    result["resized_geoms"] = refit_model_file(raw, refit)
    done = render_robomimic(py, refit, "robomimic.hdf5")
    if done.returncode != 0:
        raise RuntimeError(f"robomimic's dataset_states_to_obs.py failed on the refit file:\n{done.stderr[-3000:]}")
    result["robomimic_seconds"] = round(time.perf_counter() - started, 1)
    theirs = work / "robomimic.hdf5"
    # ours on robomimic's converted file as recorded: the recorded XML fails here too, and render-dataset falls back
    # to the task's model with the recorded geom sizes, the model of the refit copy robomimic rendered
    started = time.perf_counter()
    report = render_ours(raw, work / "ours.hdf5")
    result["files"] = {"as recorded": {"ours_seconds": round(time.perf_counter() - started, 1),
                                       "models": sorted({e["model"].split(" (")[0] for e in report["episodes"]}),
                                       "state_error": max(e["state_error"] for e in report["episodes"]),
                                       **compare_files(work / "ours.hdf5", theirs)}}
    # 3. the actions render-dataset wrote (float32) and the conversion itself (float64), against robomimic's replay
    rows = human_actions(py, work, refit, work / "ours.hdf5")
    result["robomimic"] = rows[0].pop("robomimic")
    result["actions"] = rows
    result["ok"] = (all(f["ok"] for f in result["files"].values())
                    and all(action_ok(r["converted"]) for r in rows))
    return result


def fmt(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, (int, np.integer)) or x == int(x) and abs(x) >= 1:
        return str(int(x))
    return "0" if x == 0 else f"{x:.1e}"


def action_lines(where: str, a: dict, steps: int) -> list[str]:
    later, first, k = a["later"], a["first"], a["orientation_from_step"]
    lines = [
        f"| delta -> absolute | {where} | goal position (steps 1-{steps - 1}) / orientation (steps {k}-{steps - 1}) "
        f"vs robosuite's in robomimic's replay | {fmt(later['position_max_m'])} m / "
        f"{fmt(later['orientation_max_rad'])} rad | {'pass' if action_ok(a) else 'FAIL'} |",
        f"| delta -> absolute | {where} | step 0: robosuite's controller still holds the pose of the reset before "
        f"`reset_to` (behind by {fmt(a['controller_pose_behind_first_m'])} m) | "
        f"{fmt(first['position_max_m'])} m / {fmt(first['orientation_max_rad'])} rad | "
        f"{'explained' if a['first_explained'] else 'FAIL'} |"]
    if k > 1:
        lines.append(f"| delta -> absolute | {where} | orientation, steps 1-{k - 1}: no rotation delta yet, robosuite "
                     f"keeps step 0's goal orientation | {fmt(a['orientation_carried_max_rad'])} rad | "
                     f"{'explained' if a['orientation_carried_is_step0s'] else 'FAIL'} |")
    return lines


def table_lines(result: dict) -> list[str]:
    lines = ["| check | task | compared | max difference | result |", "|---|---|---|---|---|"]
    ok = lambda r: "pass" if r else "FAIL"   # noqa: E731
    image = lambda rows: max(d["max"] for d in rows.values() if d.get("kind") == "image")   # noqa: E731
    low = lambda rows: max(d["max"] for d in rows.values() if d.get("kind") == "low-dim")   # noqa: E731
    for task, r in result["tasks"].items():
        n = r["states"]
        for key, d in r["obs"].items():
            what = "pixels (0-255), exact" if d.get("kind") == "image" else "ours float32, robomimic float64"
            lines.append(f"| observation of a state | {task} | {key}: {n} states, {what} | {fmt(d['max'])} | "
                         f"{ok(d['ok'])} |")
        a = r["actions"]
        lines += action_lines(task, a, n)
        lines.append(f"| absolute replay | {task} | state one step after each state, steps 1-{n - 1} (step 0: "
                     f"{fmt(a['state_first'])}, the goals above) | {fmt(a['state_later'])} | "
                     f"{ok(a['state_later'] <= STATE_TOL)} |")
        s = r["step_obs"]
        lines.append(f"| step observation | {task} | ours vs robomimic's observation of the state its step reached "
                     f"(pixels / low-dim) | {fmt(image(s['vs_next_state_obs']))} / {fmt(low(s['vs_next_state_obs']))} "
                     f"| {ok(all(d['ok'] for d in s['vs_next_state_obs'].values()))} |")
        for which, what in (("vs_robomimic_step_return", "what robomimic's `step` returns"),
                            ("vs_robomimic_after_step", "robomimic's `get_observation()` after its step")):
            lines.append(f"| step observation | {task} | ours vs {what} (pixels / low-dim) | "
                         f"{fmt(image(s[which]))} / {fmt(low(s[which]))} | explained |")
    d = result.get("datasets")
    if d:
        lines.append(f"| dataset_states_to_obs on the file as recorded | Lift, robosuite's human demos | exit "
                     f"{d['robomimic_as_recorded']['returncode']}: {d['robomimic_as_recorded']['error'][:70]}... "
                     f"| - | explained |")
        for label, f in d["files"].items():
            for key, row in f["keys"].items():
                lines.append(f"| render-dataset vs dataset_states_to_obs | Lift, robosuite's human demos | {key}: "
                             f"{row['frames']} frames | {fmt(row['max'])} | {ok(row['ok'])} |")
        for row in d["actions"]:
            where = f"Lift, human {row['demo']}"
            lines += action_lines(where, row["converted"], row["steps"])
            w = row["written_float32"]["later"]
            lines.append(f"| delta -> absolute | {where} | the actions render-dataset wrote (float32), as above | "
                         f"{fmt(w['position_max_m'])} m / {fmt(w['orientation_max_rad'])} rad | explained |")
            k = row["converted"]["orientation_from_step"]
            lines.append(f"| absolute replay | {where} | state one step after each state, written float32 actions, "
                         f"steps {k}-{row['steps'] - 1} (steps 1-{k - 1}: {fmt(row['state_before_rotation'])}, the "
                         f"orientations above) | {fmt(row['state_from_rotation'])} | explained |")
    return lines


def write_table(path: Path, result: dict, args: str) -> None:
    r = next(iter(result["tasks"].values()))["robomimic"] if result["tasks"] else result["datasets"]["robomimic"]
    head = (f"# Parity of our robomimic tasks with robomimic {r['robomimic']}\n\nWritten by `make interop` "
            f"(scripts/interop_robomimic.py {args}) on {datetime.date.today()}; do not edit by hand. robomimic "
            f"{r['robomimic']} ran in its own venv with robosuite {r['robosuite']} and mujoco {r['mujoco']}, as ours "
            f"does; images {SIZE} x {SIZE}, cameras {', '.join(CAMERAS)}. docs/data_interop.md explains each row.\n")
    path.write_text(head + "\n" + "\n".join(table_lines(result)) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robomimic-python", required=True, help="python of robomimic's venv")
    parser.add_argument("--steps", type=int, default=20, help="delta actions per task in robomimic's rollout")
    parser.add_argument("--demos", type=int, default=3, help="robosuite's human Lift demonstrations rendered (1-3)")
    parser.add_argument("--demo-steps", type=int, help="only the first N steps of each demonstration")
    parser.add_argument("--tasks", nargs="*", default=list(TASKS), choices=TASKS)
    parser.add_argument("--skip-datasets", action="store_true", help="only the per-task checks (1) and (3)")
    parser.add_argument("--table", type=Path, help="write the table (markdown) here")
    parser.add_argument("--out", default="interop_out")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    started = time.perf_counter()
    result: dict = {"tasks": {}}
    with tempfile.TemporaryDirectory(prefix="jepa-robomimic-") as tmp:
        for task in args.tasks:
            result["tasks"][task] = check_task(task, args.robomimic_python, Path(tmp), args.steps)
        if not args.skip_datasets:
            result["datasets"] = check_datasets(args.robomimic_python, Path(tmp), args.demos, args.demo_steps)
    result["seconds"] = round(time.perf_counter() - started, 1)
    result["ok"] = all(r["ok"] for r in result["tasks"].values()) and result.get("datasets", {}).get("ok", True)
    result["run_id"] = os.environ.get("INTEROP_RUN_ID")   # scripts/interop.sh's, for its summary
    print("\n".join(table_lines(result)))
    (out / "robomimic.json").write_text(json.dumps(result, indent=2, default=str))
    if args.table:
        write_table(args.table, result, " ".join(sys.argv[1:]).replace(str(args.robomimic_python), "PY"))
    print(f"robomimic parity: {'passed' if result['ok'] else 'FAILED'} in {result['seconds']} s "
          f"(details in {out / 'robomimic.json'})")
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
