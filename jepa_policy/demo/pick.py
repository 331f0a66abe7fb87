"""jepa-demo --task Lift | Can: the method end to end on a robomimic pick task, on this machine's CPU.

1. scripted demonstrations (``jepa_envs.tasks.robosuite_expert``) at the preset's image size, the table's
   reflection off (4.5x faster software frames; docs/envs_simulation.md), written once and reused;
2. JEPA Policy and MIP trained with the same seed, data and budget (the task's ``cpu`` preset) in parallel
   single-threaded processes, the EMA weights kept every ``snapshot_every`` steps for the learning curve;
3. the imitation ceiling of the same demonstrations: an MLP that sees the true state (the robot's proprioception
   and the object's pose), trained with the image policies' chunking and rolled out on the same episodes;
4. each arm's final EMA weights on ``eval_episodes`` fresh seeds, with Wilson intervals and every failure named
   from the simulator state (``jepa_envs/tasks/outcomes.py``); the learning curve from the kept weights on a
   block of seeds of its own; a few rollout frames;
5. Lift only: robosuite's shipped human demonstrations (``human_check``): the trained policy's action error on
   them beside held-out scripted demonstrations, and its success from their initial states;
6. ``report.md`` (tables, learning curves, frames), ``summary.json``, ``records.jsonl``.

Seeds: demonstrations from 0 (and their retries), held-out demonstrations from ``HELD_OUT_SEED``, evaluation
from ``EVAL_SEED``, the curve from ``CURVE_SEED``: no block overlaps another, and nothing is tuned on them.
Reruns reuse the demonstrations and finished training runs unless ``fresh``.

One module of about 650 lines on purpose: the six steps above, in their order, each a few functions that only
this job calls (``demo/job.py`` is PushT's job, ``demo/ceiling.py`` PushT's ceiling).
"""
from __future__ import annotations

import gzip
import json
import math
import multiprocessing
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import robosuite
import torch
from tqdm import tqdm

from jepa_envs.datasets.hdf5 import demo_names, load_dataset, open_hdf5, write_dataset
from jepa_envs.datasets.render_dataset import render_dataset
from jepa_envs.tasks.outcomes import FAILURE_KINDS
from jepa_envs.tasks.robosuite_expert import generate_demos
from jepa_envs.tasks.rotations import rot6d_to_matrix
from jepa_envs.tasks.spec import get_task_spec
from jepa_policy.checkpoint import load_checkpoint
from jepa_policy.demo.ceiling import StatePolicy
from jepa_policy.dataset import window_indices
from jepa_policy.evaluate import env_kwargs_for, evaluate, make_pool
from jepa_policy.policy import Policy
from jepa_policy.progress import Timer, bars_disabled
from jepa_policy.selection import wilson_ci
from jepa_policy.train import load_config, train

TASKS = ("Lift", "Can")
ARMS = ("jepa", "mip")
HELD_OUT_SEED = 100_000   # scripted demonstrations the policies never trained on (the human-data comparison)
EVAL_SEED = 200_000       # the final evaluation
CURVE_SEED = 300_000      # the learning curve's rollouts


@dataclass(frozen=True)
class PickConfig:
    """Budget of one run of the pick job."""

    task: str
    mode: str = "default"
    demos: int = 200
    preset: str = "cpu"
    seed: int = 42
    eval_episodes: int = 200
    curve_episodes: int = 10
    snapshot_every: int = 500
    held_out_demos: int = 20
    ceiling_steps: int = 4000
    num_envs: int = 4
    workers: int = 2               # rollout processes (rendering dominates a robosuite step)
    max_steps: int | None = None   # an episode's step limit (None: the task's, 400)
    human: bool = True             # Lift: the human-demonstration check
    train_overrides: dict = field(default_factory=dict)

    @property
    def image_size(self) -> int:
        return load_config(self.task, self.preset).image_size or get_task_spec(self.task).image_size


def pick_config(task: str, mode: str = "default", steps: int | None = None) -> PickConfig:
    if task not in TASKS:
        raise ValueError(f"the pick job runs {', '.join(TASKS)}; got {task!r} (jepa-demo without --task runs PushT)")
    if mode == "quick":
        cfg = PickConfig(task, mode="quick", demos=3, preset="cpu", eval_episodes=4, curve_episodes=2,
                         snapshot_every=10, held_out_demos=2, ceiling_steps=40, num_envs=2, workers=0,
                         max_steps=16, human=False,
                         train_overrides={"steps": 20, "warmup_steps": 2, "batch_size": 8, "image_size": 32,
                                          "log_every": 5, "ckpt_every": 20})
    else:
        cfg = PickConfig(task)
    if steps is not None:
        if steps < 1:
            raise ValueError(f"--steps must be a positive number of training steps, got {steps}")
        cfg = replace(cfg, train_overrides={**cfg.train_overrides, "steps": steps})
    return cfg


# ----------------------------------------------------------------------------- 1. demonstrations

def _image_size(cfg: PickConfig) -> int:
    return int(cfg.train_overrides.get("image_size") or cfg.image_size)


def make_demos(cfg: PickConfig, out: Path, fresh: bool, count: int, seed: int, name: str) -> Path:
    """``count`` scripted demonstrations from ``seed`` at the run's image size, the reflection off; reused."""
    path = out / "data" / f"{cfg.task.lower()}_{name}_{count}demos_{_image_size(cfg)}px.hdf5"
    if path.exists() and not fresh:
        print(f"   reusing {path}", flush=True)
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    episodes, env_args = generate_demos(cfg.task, count, seed=seed, image_size=_image_size(cfg),
                                        workers=max(1, cfg.workers), progress=not bars_disabled(),
                                        reflections=False)
    tmp = path.with_suffix(".tmp.hdf5")
    write_dataset(tmp, episodes, env_args)
    tmp.replace(path)
    e = env_args["expert"]
    print(f"   {len(episodes)} demonstrations ({e['successes']}/{e['attempts']} expert attempts succeeded), "
          f"{sum(len(x['actions']) for x in episodes)} steps -> {path}", flush=True)
    return path


# ----------------------------------------------------------------------------- 2. training

def train_arm(task: str, preset: str, arm: str, seed: int, dataset: Path, run_dir: Path, overrides: dict,
              fresh: bool, threads: int | None = None) -> Path:
    """One arm with the shared preset; a finished run of the same config and data is reused."""
    if threads:
        torch.set_num_threads(threads)
    tcfg = load_config(task, preset, **{**overrides, "arm": arm, "seed": seed, "dataset": str(dataset),
                                        "out_dir": str(run_dir)})
    ckpt = run_dir / "checkpoints" / "latest.pt"
    stamp = run_dir / "job_config.json"
    st = dataset.stat()
    wanted = {"train": tcfg.to_dict(), "dataset": [str(dataset.resolve()), st.st_size, st.st_mtime_ns]}
    stamped = json.loads(stamp.read_text()) if stamp.exists() else {}
    stamped.pop("wall_s", None)   # the finished run's own wall time, not part of what it was asked for
    if ckpt.exists() and stamp.exists() and not fresh and stamped == wanted:
        if int(load_checkpoint(ckpt)["step"]) == tcfg.steps:
            print(f"   reusing {ckpt}", flush=True)
            return ckpt
    if run_dir.exists():
        shutil.rmtree(run_dir)
    t0 = time.perf_counter()
    train(tcfg)
    wanted["wall_s"] = time.perf_counter() - t0
    stamp.write_text(json.dumps(wanted, indent=2))
    return ckpt


def train_arms(cfg: PickConfig, dataset: Path, out: Path, fresh: bool) -> dict[str, Path]:
    """Both arms at once, one single-threaded process each (one per core on this machine)."""
    overrides = {"eval_every": cfg.snapshot_every, "eval_episodes": 0, "keep_eval_checkpoints": True,
                 **cfg.train_overrides}
    runs = {arm: out / "runs" / f"{arm}_seed{cfg.seed}" for arm in ARMS}
    if (os.cpu_count() or 1) < 2:
        return {arm: train_arm(cfg.task, cfg.preset, arm, cfg.seed, dataset, runs[arm], overrides, fresh)
                for arm in ARMS}
    with ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {arm: pool.submit(train_arm, cfg.task, cfg.preset, arm, cfg.seed, dataset, runs[arm], overrides,
                                    fresh, 1) for arm in ARMS}
        return {arm: f.result() for arm, f in futures.items()}


def training_wall_s(checkpoint: Path) -> float | None:
    stamp = Path(checkpoint).parent.parent / "job_config.json"
    return json.loads(stamp.read_text()).get("wall_s") if stamp.exists() else None


# ----------------------------------------------------------------------------- 3. the imitation ceiling

class PickStates:
    """The true state of a pick task read from its simulator: the robot's low-dim observation (grip-site
    position and orientation, finger positions) and the object's position and orientation (quaternion)."""

    def __init__(self, env):
        self.env = env.unwrapped
        backend = self.env.backend
        if type(backend).__name__ == "Lift":
            self.body = int(backend.cube_body_id)
        else:
            obj = backend.objects[backend.object_id]
            self.body = int(backend.obj_body_id[obj.name])
        self.lowdim = [k for k, _ in self.env.task_spec.lowdim]

    def now(self, obs: dict) -> np.ndarray:
        data = self.env.backend.sim.data
        return np.concatenate([*(np.asarray(obs[k], np.float64).ravel() for k in self.lowdim),
                               data.body_xpos[self.body], data.body_xquat[self.body]])

    def of_state(self, state: np.ndarray, obs: dict) -> np.ndarray:
        self.env.set_sim_state(state)
        return self.now(obs)


def demo_states(task: str, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true states (N, d), actions (N, A), episode ends) of a pick demonstration file, the states read back
    from its recorded MuJoCo states."""
    spec = get_task_spec(task)
    env = gym.make(spec.env_id, image_size=16)
    env.unwrapped.set_render_images(False)
    states = PickStates(env)
    rows, actions, ends = [], [], []
    try:
        env.reset(seed=0)
        with open_hdf5(path) as f:
            for name in demo_names(f["data"]):
                demo = f["data"][name]
                lowdim = {k: demo["obs"][k][:] for k in states.lowdim}
                for t, mj in enumerate(demo["states"][:]):
                    rows.append(states.of_state(mj, {k: v[t] for k, v in lowdim.items()}))
                actions.append(demo["actions"][:])
                ends.append(sum(len(a) for a in actions))
    finally:
        env.close()
    return np.asarray(rows), np.concatenate(actions).astype(np.float32), np.asarray(ends)


def train_state_policy(task: str, path: Path, steps: int, seed: int, batch_size: int = 256, lr: float = 1e-3,
                       warmup: int = 200) -> tuple[StatePolicy, dict]:
    spec = get_task_spec(task)
    states, actions, ends = demo_states(task, path)
    idx = window_indices(ends, spec.obs_steps, spec.horizon, future_k=0)
    torch.manual_seed(seed)
    policy = StatePolicy(spec.obs_steps, spec.horizon, actions.shape[1], state_dim=states.shape[1],
                         featurize=np.asarray)   # the true state as it is
    raw = states[idx.obs].reshape(len(idx.obs), -1)
    policy.x_mean.copy_(torch.as_tensor(raw.mean(0), dtype=torch.float32))
    policy.x_std.copy_(torch.as_tensor(raw.std(0) + 1e-6, dtype=torch.float32))
    policy.a_low.copy_(torch.as_tensor(actions.min(0)))
    policy.a_high.copy_(torch.as_tensor(np.maximum(actions.max(0), actions.min(0) + 1e-6)))
    x = policy.features(states[idx.obs])
    y = policy.scale(torch.as_tensor(actions[idx.action]))
    opt = torch.optim.AdamW(policy.parameters(), lr=lr, weight_decay=1e-6)
    warm = max(1, min(warmup, steps))
    schedule = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: min(1.0, (i + 1) / warm) * 0.5 * (1 + math.cos(math.pi * i / steps)))
    gen = torch.Generator().manual_seed(seed)
    losses = []
    policy.train()
    for _ in range(steps):
        b = torch.randint(0, len(x), (min(batch_size, len(x)),), generator=gen)
        loss = ((policy(x[b]) - y[b]) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        schedule.step()
        losses.append(loss.detach().item())
    policy.eval()
    return policy, {"windows": int(len(x)), "final_loss": float(np.mean(losses[-100:])), "steps": steps}


def evaluate_state_policy(task: str, policy: StatePolicy, episodes: int, seed: int,
                          max_steps: int | None = None) -> list[dict]:
    """Seeded rollouts (episode i from seed + i), re-planning every ``n_action_steps``; no frame is rendered."""
    spec = get_task_spec(task)
    env = gym.make(spec.env_id, image_size=16)
    env.unwrapped.set_render_images(False)
    states = PickStates(env)
    limit = max_steps or spec.max_episode_steps
    records = []
    try:
        for e in tqdm(range(episodes), desc=f"{task} true-state policy", unit="ep"):
            obs, info = env.reset(seed=seed + e)
            history = [states.now(obs)] * policy.obs_steps
            plan, k, t, done = None, 0, 0, False
            while not done:
                if plan is None or k >= spec.n_action_steps:
                    plan, k = policy.act(np.stack(history[-policy.obs_steps:])), 0
                obs, _, terminated, truncated, info = env.step(plan[k])
                k, t = k + 1, t + 1
                history.append(states.now(obs))
                done = terminated or truncated or t >= limit
            success = bool(info["is_success"])
            records.append({"seed": seed + e, "success": success, "length": t, "arm": "state",
                            "failure_kind": None if success else FAILURE_KINDS[int(info["failure_kind"])]})
    finally:
        env.close()
    return records


# ----------------------------------------------------------------------------- 4. evaluation

def rate(records: list[dict]) -> dict:
    k, n = sum(r["success"] for r in records), len(records)
    kinds = {kind: sum(r.get("failure_kind") == kind for r in records) for kind in FAILURE_KINDS[1:]}
    lengths = [r["length"] for r in records if r["success"]]
    return {"successes": k, "episodes": n, "rate": k / n if n else None, "ci95": list(wilson_ci(k, n)) if n else None,
            "failure_kinds": {k_: v for k_, v in kinds.items() if v},
            "median_success_length": float(np.median(lengths)) if lengths else None}


def evaluate_checkpoint(checkpoint: Path, episodes: int, seed: int, cfg: PickConfig, tags: dict,
                        desc: str, keep_latents: bool = False) -> list[dict]:
    """Records of ``episodes`` rollouts from ``seed`` on, each with its decisions (NMSE, the detectors' scores
    and, with ``keep_latents``, the predicted and realized future latents the monitor takes)."""
    policy = Policy.from_checkpoint(checkpoint)
    pool = make_pool(policy, min(cfg.num_envs, episodes), workers=cfg.workers, max_steps=cfg.max_steps)
    records = []
    try:
        with tqdm(total=episodes, desc=desc, unit="ep") as bar:
            for start in range(0, episodes, cfg.num_envs):
                n = min(cfg.num_envs, episodes - start)
                report = evaluate(policy, episodes=n, seed=seed + start, num_envs=n, pool=pool, tags=tags,
                                  keep_latents=keep_latents)
                records += report["records"]
                bar.update(n)
    finally:
        pool.close()
    return records


def learning_curve(cfg: PickConfig, checkpoints: dict[str, Path]) -> dict[str, list[dict]]:
    """Success of each kept EMA snapshot (and the final weights) on the curve's block of seeds."""
    curve = {}
    for arm, ckpt in checkpoints.items():
        points = []
        snapshots = sorted(Path(ckpt).parent.glob("eval_step*.pt"), key=lambda p: int(p.stem.split("step")[1]))
        for snap in snapshots:
            step = int(snap.stem.split("step")[1])
            records = evaluate_checkpoint(snap, cfg.curve_episodes, CURVE_SEED, cfg,
                                          {"arm": arm, "phase": "curve", "checkpoint_step": step},
                                          f"{arm} step {step}")
            points.append({"step": step, **rate(records)})
        curve[arm] = points
    return curve


def rollout_frames(checkpoint: Path, seed: int, count: int = 6,
                   max_steps: int | None = None) -> list[tuple[str, np.ndarray]]:
    """Frames of one rollout (both cameras side by side) for the report."""
    policy = Policy.from_checkpoint(checkpoint)
    env = gym.make(policy.spec.env_id, **env_kwargs_for(policy.spec, policy.env_args))
    frames, success = [], False
    try:
        obs, _ = env.reset(seed=seed)
        policy.reset()
        done, t = False, 0
        while not done:
            frames.append((t, np.concatenate([obs[k] for k in policy.spec.image_keys], axis=1)))
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            success |= bool(info["is_success"])
            done, t = terminated or truncated or t + 1 == max_steps, t + 1
        frames.append((t, np.concatenate([obs[k] for k in policy.spec.image_keys], axis=1)))
    finally:
        env.close()
    picks = np.linspace(0, len(frames) - 1, count).round().astype(int)
    return [(f"step {frames[i][0]}" + (f" ({'success' if success else 'failure'})" if i == picks[-1] else ""),
             frames[i][1]) for i in picks]


# ----------------------------------------------------------------------------- 5. human data (Lift)

HUMAN_LIFT = "models/assets/demonstrations/lift/demo.hdf5"   # inside the robosuite package: 3 human demos


def human_demos_file() -> Path:
    return Path(robosuite.__file__).parent / HUMAN_LIFT


def action_errors(policy: Policy, dataset: Path, batch: int = 64) -> dict:
    """The policy's first predicted action against each recorded action of ``dataset`` (the window of its
    ``obs_steps`` newest frames, padded at an episode's start as in training): grip-site position error (cm),
    orientation error (degrees) and whether the gripper command has the recorded sign."""
    demos = load_dataset(dataset, task=policy.spec.name, image_size=policy.spec.image_size, cache_dir=False)
    starts = np.concatenate([[0], demos.episode_ends[:-1]])
    start_of = np.repeat(starts, np.diff(np.concatenate([[0], demos.episode_ends])))
    keys = [*policy.spec.image_keys, *(k for k, _ in policy.spec.lowdim)]
    predicted = []
    for lo in range(0, len(demos), batch):
        t = np.arange(lo, min(lo + batch, len(demos)))
        frames = [{k: demos.obs[k][np.maximum(t - back, start_of[t])] for k in keys}
                  for back in range(policy.obs_steps - 1, -1, -1)]
        predicted.append(policy.decide_from(frames, want_future=False).actions[:, 0])
    predicted = np.concatenate(predicted).astype(np.float64)
    recorded = demos.actions.astype(np.float64)
    pos = np.linalg.norm(predicted[:, :3] - recorded[:, :3], axis=1) * 100
    rel = np.einsum("nij,nik->njk", rot6d_to_matrix(predicted[:, 3:9]), rot6d_to_matrix(recorded[:, 3:9]))
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    grip = np.sign(predicted[:, 9]) == np.sign(recorded[:, 9])
    return {"steps": int(len(recorded)), "episodes": demos.num_episodes(),
            "position_cm": {"median": float(np.median(pos)), "p90": float(np.percentile(pos, 90))},
            "orientation_deg": {"median": float(np.median(angle)), "p90": float(np.percentile(angle, 90))},
            "gripper_agreement": float(grip.mean())}


def success_from_states(policy: Policy, dataset: Path, max_steps: int | None = None) -> list[dict]:
    """The policy from each episode's recorded first state of ``dataset`` (its own frames from there on)."""
    env = gym.make(policy.spec.env_id, **env_kwargs_for(policy.spec, policy.env_args))
    out = []
    try:
        with open_hdf5(dataset) as f:
            firsts = [(name, f["data"][name]["states"][0]) for name in demo_names(f["data"])]
        for name, state in firsts:
            obs, info = env.reset(seed=0, options={"state": state})
            policy.reset()
            done, t = False, 0
            while not done:
                obs, _, terminated, truncated, info = env.step(policy.act(obs))
                done, t = terminated or truncated or t + 1 == max_steps, t + 1
            success = bool(info["is_success"])
            out.append({"demo": name, "success": success, "length": t,
                        "failure_kind": None if success else FAILURE_KINDS[int(info["failure_kind"])]})
    finally:
        env.close()
    return out


def human_check(cfg: PickConfig, out: Path, checkpoints: dict[str, Path], held_out: Path, fresh: bool) -> dict:
    """robosuite's shipped human Lift demonstrations, rendered as the policies see (render-dataset, the run's
    size, the reflection off): action errors on them beside held-out scripted demonstrations, and success from
    their initial states."""
    human = out / "data" / f"lift_human_{_image_size(cfg)}px.hdf5"
    if fresh or not human.exists():
        human.parent.mkdir(parents=True, exist_ok=True)
        render_dataset(human_demos_file(), human, task="Lift", size=_image_size(cfg), progress=not bars_disabled(),
                       reflections=False)
    result = {"human_file": str(human), "arms": {}}
    for arm, ckpt in checkpoints.items():
        policy = Policy.from_checkpoint(ckpt)
        result["arms"][arm] = {"human": action_errors(policy, human),
                               "scripted_held_out": action_errors(policy, held_out),
                               "from_human_starts": success_from_states(policy, human, cfg.max_steps)}
    return result


# ----------------------------------------------------------------------------- 6. the report

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_curves(curve: dict[str, list[dict]], final: dict[str, dict], ceiling: dict, run_dirs: dict[str, Path],
                path: Path) -> None:
    plt = _plt()
    fig, (ax_loss, ax_eval) = plt.subplots(1, 2, figsize=(10, 3.6))
    for arm, run_dir in run_dirs.items():
        rows = [json.loads(x) for x in (run_dir / "log.jsonl").read_text().splitlines() if '"loss_act"' in x]
        ax_loss.plot([r["step"] for r in rows], [r["loss_act"] for r in rows], label=arm.upper())
    for arm, points in curve.items():
        steps = [p["step"] for p in points]
        rates = [100 * p["rate"] for p in points]
        low = [100 * (p["rate"] - p["ci95"][0]) for p in points]
        high = [100 * (p["ci95"][1] - p["rate"]) for p in points]
        ax_eval.errorbar(steps, rates, yerr=[low, high], marker="o", capsize=3, label=f"{arm.upper()} (curve seeds)")
    ax_eval.axhline(100 * ceiling["rate"], color="grey", ls="--", lw=1, label="true-state ceiling")
    ax_loss.set(xlabel="gradient step", ylabel="action loss", yscale="log", title="training loss")
    ax_eval.set(xlabel="gradient step", ylabel="success rate (%)", ylim=(-5, 105),
                title="EMA snapshots, 95 % Wilson intervals")
    for ax in (ax_loss, ax_eval):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def save_frames(rows: dict[str, list[tuple[str, np.ndarray]]], path: Path) -> None:
    plt = _plt()
    n = max(len(v) for v in rows.values())
    fig, axes = plt.subplots(len(rows), n, figsize=(2.4 * n, 1.5 * len(rows) + 0.4), squeeze=False)
    for r, (label, frames) in enumerate(rows.items()):
        for c in range(n):
            ax = axes[r][c]
            ax.axis("off")
            if c < len(frames):
                ax.imshow(frames[c][1])
                ax.set_title(f"{label}: {frames[c][0]}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _pct(r: dict) -> str:
    lo, hi = r["ci95"]
    return f"{r['successes']}/{r['episodes']} = {100 * r['rate']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}]"


def render_report(summary: dict) -> str:
    cfg, s = summary["config"], summary
    lines = [f"# JEPA Policy and MIP on {cfg['task']} (robomimic), learned from scripted demonstrations on a CPU", "",
             f"Every number below is what `jepa-demo --task {cfg['task']}` measured in this run "
             f"({s['wall_s'] / 60:.0f} min on {s['machine']['cores']} cores; "
             f"load average {s['machine']['load_before']} "
             f"before, {s['machine']['load_after']} after).", "",
             "## Data and training", "",
             f"- {s['demos']['episodes']} scripted demonstrations ({s['demos']['expert_successes']}/"
             f"{s['demos']['expert_attempts']} expert attempts succeeded; {s['demos']['steps']} steps), "
             f"{cfg['image_size']} px, cameras {', '.join(s['demos']['cameras'])}, the table's reflection off.",
             f"- Preset `{cfg['preset']}` (`jepa_policy/configs/{cfg['task']}.json`): {s['train']['steps']} steps, "
             f"batch {s['train']['batch_size']}; the two arms trained at once, one core each.", ""]
    lines += ["| arm | training wall time | samples/s |", "|---|---|---|"]
    for arm, t in s["train"]["arms"].items():
        wall = "reused" if t["wall_s"] is None else f"{t['wall_s'] / 60:.1f} min"
        lines.append(f"| {arm.upper()} | {wall} | {t['samples_per_s']:.0f} |")
    lines += ["", f"## Success on {cfg['eval_episodes']} fresh seeds (from {EVAL_SEED:,})", "",
              "| policy | success (95 % Wilson) | median length of a success | failures by kind |", "|---|---|---|---|"]
    for label, r in s["final"].items():
        kinds = ", ".join(f"{k} {v}" for k, v in r["failure_kinds"].items()) or "-"
        med = "-" if r["median_success_length"] is None else f"{r['median_success_length']:.0f}"
        lines.append(f"| {label} | {_pct(r)} | {med} | {kinds} |")
    lines += ["", "The ceiling is an MLP on the true state (proprioception and the object's pose) trained on the same "
              "demonstrations with the same chunking: what imitation of these demonstrations reaches with perfect "
              "perception. Failure kinds are named from the simulator state (`jepa_envs/tasks/outcomes.py`).", "",
              f"## Learning curve ({cfg['curve_episodes']} episodes per point, seeds from {CURVE_SEED:,})", "",
              "![curves](curves.png)", "", "| step | " + " | ".join(a.upper() for a in s["curve"]) + " |",
              "|---|" + "---|" * len(s["curve"])]
    steps = sorted({p["step"] for pts in s["curve"].values() for p in pts})
    for step in steps:
        cells = []
        for pts in s["curve"].values():
            p = next((p for p in pts if p["step"] == step), None)
            cells.append("-" if p is None else _pct(p))
        lines.append(f"| {step} | " + " | ".join(cells) + " |")
    lines += ["", "## Rollouts", "", "![frames](frames.png)", ""]
    if s.get("human"):
        h = s["human"]
        lines += ["## robosuite's human demonstrations (what imitation of scripted data does on human states)", "",
                  "| arm | data | steps | position error median / p90 (cm) | orientation median / p90 (deg) | "
                  "gripper sign agrees |", "|---|---|---|---|---|---|"]
        for arm, r in h["arms"].items():
            for name, e in (("human (3 demos)", r["human"]), ("held-out scripted", r["scripted_held_out"])):
                lines.append(f"| {arm.upper()} | {name} | {e['steps']} | {e['position_cm']['median']:.2f} / "
                             f"{e['position_cm']['p90']:.2f} | {e['orientation_deg']['median']:.1f} / "
                             f"{e['orientation_deg']['p90']:.1f} | {100 * e['gripper_agreement']:.0f} % |")
        lines += ["", "From the human demonstrations' initial states: " + "; ".join(
            f"{arm.upper()} {sum(x['success'] for x in r['from_human_starts'])}/{len(r['from_human_starts'])}"
            for arm, r in h["arms"].items()) + ".", ""]
    lines += ["## Wall time per step", "", "| step | seconds |", "|---|---|"]
    lines += [f"| {name} | {sec:.0f} |" for name, sec in s["timer"].items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- the job

def _samples_per_s(run_dir: Path) -> float:
    rows = [json.loads(x) for x in (run_dir / "log.jsonl").read_text().splitlines() if '"samples_per_s"' in x]
    return float(np.median([r["samples_per_s"] for r in rows])) if rows else float("nan")


def run(cfg: PickConfig, out: Path, fresh: bool = False) -> dict:
    """The whole pick job into ``out``; returns the summary (also ``summary.json``)."""
    out.mkdir(parents=True, exist_ok=True)
    timer = Timer()
    load_before = " ".join(f"{x:.1f}" for x in os.getloadavg())
    with timer.step("1/6 scripted demonstrations"):
        dataset = make_demos(cfg, out, fresh, cfg.demos, 0, "train")
        held_out = make_demos(cfg, out, fresh, cfg.held_out_demos, HELD_OUT_SEED, "heldout")
    with timer.step("2/6 training JEPA Policy and MIP (same seed, data and budget, in parallel)"):
        checkpoints = train_arms(cfg, dataset, out, fresh)
    with timer.step("3/6 imitation ceiling (true-state policy, same demonstrations and episodes)"):
        state_policy, fit = train_state_policy(cfg.task, dataset, cfg.ceiling_steps, cfg.seed)
        ceiling_records = evaluate_state_policy(cfg.task, state_policy, cfg.eval_episodes, EVAL_SEED, cfg.max_steps)
    with timer.step(f"4/6 evaluation on {cfg.eval_episodes} fresh seeds and the learning curve"):
        records = ceiling_records[:]
        final = {}
        for arm, ckpt in checkpoints.items():
            recs = evaluate_checkpoint(ckpt, cfg.eval_episodes, EVAL_SEED, cfg, {"arm": arm, "phase": "final"},
                                       f"{arm} final", keep_latents=True)
            records += recs
            final[arm.upper()] = rate(recs)
        final["true-state ceiling"] = rate(ceiling_records)
        curve = learning_curve(cfg, checkpoints)
        frames = {arm.upper(): rollout_frames(ckpt, EVAL_SEED, max_steps=cfg.max_steps)
                  for arm, ckpt in checkpoints.items()}
    human = None
    if cfg.task == "Lift" and cfg.human:
        with timer.step("5/6 robosuite's human demonstrations"):
            human = human_check(cfg, out, checkpoints, held_out, fresh)
    with timer.step("6/6 report"):
        spec = get_task_spec(cfg.task)
        with open_hdf5(dataset) as f:
            expert = json.loads(f["data"].attrs["env_args"])["expert"]
            steps = sum(f["data"][n]["actions"].shape[0] for n in demo_names(f["data"]))
        tcfg = load_config(cfg.task, cfg.preset, **cfg.train_overrides)
        run_dirs = {arm: Path(ckpt).parent.parent for arm, ckpt in checkpoints.items()}
        summary = {
            "config": {**asdict(cfg), "image_size": _image_size(cfg)},
            "machine": {"cores": os.cpu_count(), "load_before": load_before,
                        "load_after": " ".join(f"{x:.1f}" for x in os.getloadavg())},
            "demos": {"episodes": cfg.demos, "steps": steps, "expert_attempts": expert["attempts"],
                      "expert_successes": expert["successes"], "cameras": list(spec.cameras), "file": str(dataset)},
            "train": {"steps": tcfg.steps, "batch_size": tcfg.batch_size,
                      "arms": {arm: {"wall_s": training_wall_s(ckpt), "samples_per_s": _samples_per_s(run_dirs[arm]),
                                     "checkpoint": str(ckpt)} for arm, ckpt in checkpoints.items()}},
            "ceiling": {**fit, **rate(ceiling_records)},
            "final": final, "curve": curve, "human": human, "timer": timer.steps,
            "wall_s": timer.total,
        }
        plot_curves(curve, final, summary["ceiling"], run_dirs, out / "curves.png")
        save_frames(frames, out / "frames.png")
        (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        with (out / "records.jsonl").open("w") as f:
            for r in records:
                f.write(json.dumps({k: v for k, v in r.items() if k != "decisions"}) + "\n")
        with gzip.open(out / "decisions.jsonl.gz", "wt") as f:   # the monitor's input: latents per decision
            for r in records:
                if "decisions" in r:
                    f.write(json.dumps(r) + "\n")
        (out / "report.md").write_text(render_report(summary))
    print(f"\n{cfg.task}: " + "; ".join(f"{label} {_pct(r)}" for label, r in final.items()), flush=True)
    print(f"report: {out / 'report.md'}  ({summary['wall_s'] / 60:.1f} min)", flush=True)
    return summary
