"""``jepa-envs bench``: what our env layer costs, and what render-on-demand saves.

Per task that can be built here, side by side in one process:
- raw backend vs our interface: steps/s of the backend's own step with its native hold-still action
  (``env.unwrapped.backend``, ``native_zero_action()``), against ``env.step`` of ``gym.make(id)`` with the
  equivalent action in our convention (``hold_action()``); overhead = raw rate / our rate - 1 (goal <= 3%).
  Both arms produce the same observation, cameras rendered: for robosuite the raw arm reads every observable
  after its step (robosuite's own ``_get_observations(force_update=True)``, as our step does; our cameras
  never sample on robosuite's clock, so a bare ``backend.step`` would render nothing and the column would
  compare rendering with not rendering). For PushT the raw backend is the pymunk simulation + the camera
  render + the coverage (reward) computation.
- render every step vs ``RenderOnDemand`` in a chunked policy loop (n_action_steps per chunk, obs_steps
  history, future frame k): steps/s and the speed-up (goal >= 2.5x).
The arms of each comparison run interleaved in blocks of one chunk, so load from other processes hits both.
Each comparison is bounded by ``--steps`` and a time budget, so the default run takes well under 2 minutes.
"""
from __future__ import annotations

import os
import sys
import time
from typing import Callable

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import jepa_envs  # noqa: F401  (registers the ids)
from jepa_envs.tasks import pusht_standard
from jepa_envs.tasks.pusht import coverage
from jepa_envs.tasks.spec import TaskSpec, all_task_specs, backend_available, get_task_spec
from jepa_envs.tasks.wrappers import RenderOnDemand, render_schedule


def interleaved_rates(arms: dict[str, Callable[[], None]], steps: int, budget_s: float, block: int) -> dict:
    """Steps/s of each zero-argument step function, run round-robin in blocks of ``block`` steps until each
    made ``steps`` steps or ``budget_s`` seconds passed. The rate is taken from the median block time, so a
    burst of load from another process on this shared machine does not decide the comparison."""
    times: dict[str, list[float]] = {k: [] for k in arms}
    start = time.perf_counter()
    while min(len(v) for v in times.values()) * block < steps and time.perf_counter() - start < budget_s:
        for name, step in arms.items():
            t0 = time.perf_counter()
            for _ in range(block):
                step()
            times[name].append(time.perf_counter() - t0)
    return {k: block / float(np.median(v)) for k, v in times.items()}


def _raw_step(env) -> Callable[[], None]:
    base = env.unwrapped
    native = base.native_zero_action()
    backend = base.backend
    if type(backend).__name__ in ("PushTSim", "StandardPushTSim"):   # pymunk sims render and score on request
        size = base.task_spec.image_size
        score = pusht_standard.coverage if type(backend).__name__ == "StandardPushTSim" else coverage
        render = (lambda: backend.render(size, size)) if score is pusht_standard.coverage else (
            lambda: backend.render(size))

        def step():
            backend.step(native)
            render()
            score(backend.block_pose)
        return step

    def step():
        backend.step(native)
        backend._get_observations(force_update=True)
    return step


def _hold_step(env, render_every_step: bool = False) -> Callable[[], None]:
    action = env.unwrapped.hold_action()
    if not render_every_step:
        return lambda: env.step(action)

    def step():
        env.unwrapped.set_render_images(True)
        env.step(action)
    return step


def _block_size(step: Callable[[], None], limit: int) -> int:
    """Steps per timed block: a chunk for fast backends, fewer (down to 1) when one step takes long."""
    t0 = time.perf_counter()
    step()
    return int(min(limit, max(1, round(0.02 / (time.perf_counter() - t0)))))


def bench_task(spec: TaskSpec, steps: int, budget_s: float) -> dict:
    """One row of the table: raw/ours steps/s and every-step/on-demand steps/s for ``spec``."""
    env = gym.make(spec.env_id, max_episode_steps=10**9)
    try:
        env.reset(seed=0)
        raw, ours = _raw_step(env), _hold_step(env)
        block = _block_size(raw, spec.n_action_steps)
        overhead = interleaved_rates({"raw": raw, "ours": ours}, steps, budget_s, block)
        # whole chunks per block: the render schedule repeats every n_action_steps steps
        demand = RenderOnDemand(env)
        demand.reset(seed=0)
        render = interleaved_rates({"every": _hold_step(env, render_every_step=True), "on_demand": _hold_step(demand)},
                                   steps, budget_s, spec.n_action_steps)
    finally:
        env.close()
    n = spec.n_action_steps
    rendered = len(render_schedule(64 * n, n, spec.obs_steps, spec.future_k)) / (64 * n)
    return {"task": spec.name, "raw": overhead["raw"], "ours": overhead["ours"],
            "overhead": overhead["raw"] / overhead["ours"] - 1.0, "every": render["every"],
            "on_demand": render["on_demand"], "speedup": render["on_demand"] / render["every"],
            "rendered_fraction": rendered}


def buildable_tasks() -> list[TaskSpec]:
    return [spec for spec in all_task_specs() if backend_available(spec.suite)[0]]


def run_bench(tasks: list[str] | None = None, steps: int = 1000, budget_s: float = 3.0,
              progress: bool = False) -> list[dict]:
    """Measure and print the table (``progress``: a bar of the tasks on stderr); tasks that fail to build are
    reported and skipped."""
    specs = [get_task_spec(t) for t in tasks] if tasks else buildable_tasks()
    print(f"jepa-envs bench: up to {steps} steps or {budget_s:.0f} s per comparison; "
          "chunked loop = n_action_steps per chunk, obs_steps history + future frame k rendered; raw and ours "
          f"both render the task's cameras; {os.cpu_count()} cores, load = 1-minute load average around the row")
    header = (f"{'task':<20}{'raw st/s':>10}{'ours st/s':>11}{'overhead':>10}  "
              f"{'every-step st/s':>16}{'on-demand st/s':>15}{'speed-up':>9}{'frames':>8}{'load':>12}")
    print(header)
    rows = []
    for spec in tqdm(specs, desc="jepa-envs bench", unit="task", disable=not progress):
        load_before = os.getloadavg()[0]
        try:
            row = bench_task(spec, steps, budget_s)
        except Exception as exc:  # one backend failing to build must not hide the others' numbers
            tqdm.write(f"{spec.name:<20}skipped: {type(exc).__name__}: {exc}", file=sys.stdout)
            continue
        row["load"] = (load_before, os.getloadavg()[0])
        rows.append(row)
        tqdm.write(f"{row['task']:<20}{row['raw']:>10.1f}{row['ours']:>11.1f}{row['overhead']:>+9.1%}  "
              f"{row['every']:>16.1f}{row['on_demand']:>15.1f}{row['speedup']:>8.2f}x{row['rendered_fraction']:>8.0%}"
              f"{row['load'][0]:>6.1f}-{row['load'][1]:<5.1f}", file=sys.stdout)
    return rows



# gym-pusht's own env, driven block by block from stdin in its own interpreter (its venv: it pins pymunk < 7);
# each block's time is taken inside that process, so the pipe costs neither arm anything
_GYM_PUSHT_CHILD = r"""
import sys, time
import numpy as np, gymnasium as gym, gym_pusht
env = gym.make("gym_pusht/PushT-v0", obs_type=sys.argv[1], render_mode="rgb_array")
actions = np.random.default_rng(0).uniform(0, 512, (int(sys.argv[2]), 2)).astype(np.float32)
env.reset(seed=0)
i = 0
print("ready", flush=True)
for line in sys.stdin:
    n = int(line)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n):
        _, _, terminated, truncated, _ = env.step(actions[i % len(actions)])
        i += 1
        if terminated or truncated:
            env.reset()
    print(time.perf_counter() - t0, time.process_time() - c0, flush=True)
"""


def bench_gym_pusht(python: str, steps: int = 1000, budget_s: float = 10.0, block: int = 50,
                    obs_types: tuple[str, ...] = ("pixels_agent_pos", "state"), progress: bool = False) -> list[dict]:
    """Steps/s of our standard PushT against gym-pusht 0.1.8's own env (run by ``python``, the interpreter of a
    venv that has gym-pusht: `make interop` builds .cache/interop/gym_pusht), interleaved in blocks of ``block``
    steps of the same uniform random targets, per gym-pusht ``obs_type`` (``pixels_agent_pos``: the 96 px image
    observation included); rates from the median block time, wall clock and CPU time (each process's own: on a
    loaded machine the wall clock also counts the time another process held the core); ``progress``: a bar of
    the rows on stderr."""
    import subprocess

    rows = []
    actions = np.random.default_rng(0).uniform(0, 512, (max(steps, block) + 1000, 2)).astype(np.float32)
    for obs_type in tqdm(obs_types, desc="gym-pusht bench", unit="row", disable=not progress):
        child = subprocess.Popen([python, "-c", _GYM_PUSHT_CHILD, obs_type, str(len(actions))], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            if child.stdout.readline().strip() != "ready":
                child.stdin.close()
                why = (child.stderr.read().strip().splitlines() or ["it exited"])[-1]
                raise ValueError(f"gym-pusht did not start in {python} ({why}); pass the python of a venv with "
                                 "gym-pusht 0.1.8 (`make interop` builds .cache/interop/gym_pusht/bin/python)")
            env = gym.make("JEPA/PushTStandard-v0", obs_type=obs_type)
            env.reset(seed=0)
            i = 0

            def ours():
                nonlocal i
                _, _, terminated, truncated, _ = env.step(actions[i % len(actions)])
                i += 1
                if terminated or truncated:
                    env.reset()

            times: dict[str, list[float]] = {"gym-pusht": [], "ours": []}
            cpu: dict[str, list[float]] = {"gym-pusht": [], "ours": []}
            load_before = os.getloadavg()[0]
            start = time.perf_counter()
            while (min(len(v) for v in times.values()) * block < steps
                   and time.perf_counter() - start < budget_s) or not times["ours"]:
                child.stdin.write(f"{block}\n")
                child.stdin.flush()
                wall, cpu_s = map(float, child.stdout.readline().split())
                times["gym-pusht"].append(wall)
                cpu["gym-pusht"].append(cpu_s)
                t0, c0 = time.perf_counter(), time.process_time()
                for _ in range(block):
                    ours()
                times["ours"].append(time.perf_counter() - t0)
                cpu["ours"].append(time.process_time() - c0)
            env.close()
        finally:
            if not child.stdin.closed:
                child.stdin.close()
            child.wait(timeout=30)
        rate = {k: block / float(np.median(v)) for k, v in times.items()}
        rate_cpu = {k: block / max(float(np.median(v)), 1e-9) for k, v in cpu.items()}
        rows.append({"obs_type": obs_type, "gym_pusht": rate["gym-pusht"], "ours": rate["ours"],
                     "ratio": rate["ours"] / rate["gym-pusht"], "gym_pusht_cpu": rate_cpu["gym-pusht"],
                     "ours_cpu": rate_cpu["ours"], "ratio_cpu": rate_cpu["ours"] / rate_cpu["gym-pusht"],
                     "blocks": len(times["ours"]),
                     "load": (load_before, os.getloadavg()[0])})
    return rows


def run_bench_gym_pusht(python: str, steps: int = 1000, budget_s: float = 10.0, progress: bool = False) -> list[dict]:
    """Measure and print the table of ``bench_gym_pusht``."""
    print(f"jepa-envs bench --gym-pusht: our PushTStandard beside gym-pusht's own env ({python}), same random "
          f"targets, interleaved blocks of 50 steps, up to {steps} steps or {budget_s:.0f} s per row; "
          f"{os.cpu_count()} cores, load = 1-minute load average around the row")
    print(f"{'obs_type':<18}{'gym-pusht st/s wall':>20}{'ours':>8}{'ratio':>8}{'gym-pusht st/s CPU':>20}{'ours':>8}"
          f"{'ratio':>8}{'load':>12}")
    rows = bench_gym_pusht(python, steps, budget_s, progress=progress)
    for r in rows:
        print(f"{r['obs_type']:<18}{r['gym_pusht']:>20.1f}{r['ours']:>8.1f}{r['ratio']:>7.2f}x"
              f"{r['gym_pusht_cpu']:>20.1f}{r['ours_cpu']:>8.1f}{r['ratio_cpu']:>7.2f}x{r['load'][0]:>6.1f}-{r['load'][1]:<5.1f}")
    return rows
