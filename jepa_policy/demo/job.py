"""jepa-demo: the whole method end to end on the embedded PushT task (the project's main job).

1. scripted PushT demonstrations (robomimic-layout HDF5);
2. JEPA Policy and MIP trained with the same seed, data and budget (the ``cpu`` preset of the paper's recipe);
3. the imitation ceiling of those demonstrations (a true-state policy, ``demo/ceiling.py``);
4. the monitor service started for real (uvicorn on loopback, SQLite file); seeded rollouts of each arm with the
   real ``MonitorClient`` in the loop: z_hat at each decision, E_rgb(o_{t+k}) when the frame arrives, the outcome
   at the end. A held-out set of labelled rollouts calibrates the task; later rollouts are scored live against
   that calibration and raise alerts;
5. decision latency, JEPA against MIP;
6. failure prediction compared: every failure signal (ours, STAC, RND, PCA-kmeans, Mahalanobis, chance) on
   several hundred more labelled rollouts per arm, natural and under faults with a known onset
   (``run_failure_study`` below, ``jepa-monitor compare``'s tables);
7. (``--full``) the audits and checkpoint selection;
8. a Markdown report with PNG figures in the output folder and a printed summary.

The steps printed while it runs are these, numbered over the ones the mode runs (the default runs 7).
The command line is ``jepa_policy/demo/cli.py``; ``--task Lift|Can`` runs ``demo/pick.py`` instead.

Every number in the report is what this run measured. Reruns reuse demos and checkpoints unless ``--fresh``.
"""
from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import secrets
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import gymnasium as gym
import httpx
import numpy as np
import torch
from tqdm import tqdm

from jepa_envs.datasets.hdf5 import load_dataset, write_dataset
from jepa_envs.tasks.pusht_expert import generate_demos
from jepa_policy.audit import audit_checkpoint, gradient_audit, retrieval_audit
from jepa_policy.bench import count_passes, time_calls
from jepa_policy.checkpoint import load_checkpoint
from jepa_policy.demo.ceiling import evaluate_state_policy, train_state_policy
from jepa_policy.demo.report import write_report
from jepa_policy.detectors import fit_detectors, load_detectors
from jepa_policy.evaluate import env_kwargs_for, evaluate, make_pool
from jepa_policy.policy import Policy
from jepa_policy.progress import Timer, bars_disabled
from jepa_policy.selection import select_checkpoint, wilson_ci
from monitor_service.offline.compare import compare as compare_signals
from monitor_service.offline.compare import episode_of
from monitor_service.offline.compare import markdown as compare_markdown
from jepa_policy.train import load_config, train
from monitor_service.client import MonitorClient
from monitor_service.server import provision, start_server

TASK = "PushT"


@dataclass(frozen=True)
class DemoConfig:
    """Budget of one run; ``MODES`` holds the three named budgets."""

    mode: str
    demos: int                 # scripted demonstrations
    preset: str                # training preset of jepa_policy/configs/PushT.json
    seeds: tuple[int, ...]     # training seeds (one per arm each)
    calib_episodes: int        # held-out, labelled rollouts per arm and seed that calibrate the task
    live_episodes: int         # later rollouts scored live against that calibration
    latency_iters: int         # timed decisions per arm (after 30 warm-up calls, or fewer in quick mode)
    latency_warmup: int
    train_overrides: dict = field(default_factory=dict)
    # coverage at which each demonstration ends (the task succeeds at 0.8): demos that finish with a margin teach
    # the policies to clear the threshold instead of landing around it (docs/training.md)
    finish_threshold: float = 0.9
    num_envs: int = 4
    # env-only rollout processes of the monitored rollouts and the selection (one persistent pool). PushT's env
    # step is cheaper than a pipe round trip: in-process measured fastest (`jepa-policy bench rollouts`)
    workers: int = 0
    bootstrap: int = 10_000
    permutations: int = 10_000
    ceiling_steps: int = 4000  # training steps of the true-state policy that measures the imitation ceiling
    # the paper's audits of every checkpoint and the leakage-free checkpoint selection (jepa-policy audit/protocols)
    audits: bool = False
    audit_samples: int = 4096
    audit_pool: int = 256
    selection_ladder: tuple[int, ...] = (32, 64, 128)
    # failure prediction compared (run_failure_study): natural rollouts per arm on a seed block of their
    # own, rollouts per fault, the training windows the embedding detectors are fitted on, bootstrap resamples
    failure_episodes: int = 0
    failure_fault_episodes: int = 0
    failure_faults: tuple[str, ...] = ()
    failure_detector_samples: int = 2048
    failure_bootstrap: int = 2000


# the failure-prediction step of the default and full modes: >= 300 labelled episodes per arm
FAILURE_BUDGET = {"failure_episodes": 320, "failure_fault_episodes": 40,
                  "failure_faults": ("block_displaced", "action_latency", "background_tint")}

MODES = {
    "quick": DemoConfig("quick", demos=6, preset="quick", seeds=(42,), calib_episodes=6, live_episodes=4,
                        latency_iters=20, latency_warmup=3, train_overrides={"steps": 30, "eval_every": 15,
                                                                             "eval_episodes": 2,
                                                                             "init_candidates": 2,
                                                                             "init_screen_steps": 6},
                        num_envs=2, bootstrap=1000, permutations=1000, ceiling_steps=30, audits=True,
                        audit_samples=64, audit_pool=32, selection_ladder=(2, 4), failure_episodes=6,
                        failure_fault_episodes=2, failure_faults=("block_displaced",), failure_detector_samples=256,
                        failure_bootstrap=200),
    "default": DemoConfig("default", demos=200, preset="cpu", seeds=(42,), calib_episodes=64, live_episodes=64,
                          latency_iters=300, latency_warmup=30, **FAILURE_BUDGET),
    "full": DemoConfig("full", demos=200, preset="cpu", seeds=(41, 42, 43), calib_episodes=64, live_episodes=40,
                       latency_iters=300, latency_warmup=30, audits=True, **FAILURE_BUDGET),
}
ARMS = ("jepa", "mip")
ROBOT = "pusht-sim"
CALIB_SEED, LIVE_SEED = 10_000, 20_000  # rollout seeds never overlap the demonstrations' seeds (0, 1, ...)


def _digest(data) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:12]


# ----------------------------------------------------------------------------- step 1: demonstrations

def make_demos(cfg: DemoConfig, out: Path, fresh: bool) -> Path:
    """Scripted expert demonstrations, reused when the same request was already written."""
    path = out / "data" / f"pusht_{cfg.demos}demos_finish{cfg.finish_threshold:g}.hdf5"
    if path.exists() and not fresh:
        print(f"   reusing {path}")
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    episodes, env_args = generate_demos(cfg.demos, seed=0, workers=os.cpu_count() or 1, progress=not bars_disabled(),
                                        finish_threshold=cfg.finish_threshold)
    tmp = path.with_suffix(".tmp.hdf5")
    write_dataset(tmp, episodes, env_args)
    tmp.replace(path)
    print(f"   {len(episodes)} demonstrations, {sum(len(e['actions']) for e in episodes)} transitions -> {path}")
    return path


# ----------------------------------------------------------------------------- step 2: training

def train_arm(cfg: DemoConfig, arm: str, seed: int, dataset: Path, out: Path, fresh: bool,
              threads: int | None = None) -> Path:
    """Train one arm with the shared preset; a finished run with the same config is reused."""
    if threads:
        torch.set_num_threads(threads)
    run_dir = out / "runs" / f"{arm}_seed{seed}"
    overrides = dict(cfg.train_overrides, arm=arm, seed=seed, dataset=str(dataset), out_dir=str(run_dir))
    tcfg = load_config(TASK, cfg.preset, **overrides)
    ckpt = run_dir / "checkpoints" / "latest.pt"
    stamp = run_dir / "demo_config.json"
    wanted = {"train": tcfg.to_dict(), "dataset_digest": _file_digest(dataset)}
    if ckpt.exists() and stamp.exists() and not fresh and json.loads(stamp.read_text()) == wanted:
        if int(load_checkpoint(ckpt)["step"]) == tcfg.steps:
            print(f"   reusing {ckpt}", flush=True)
            return ckpt
    if run_dir.exists():
        shutil.rmtree(run_dir)
    train(tcfg)
    stamp.write_text(json.dumps(wanted, indent=2))
    return ckpt


def train_all(cfg: DemoConfig, dataset: Path, out: Path, fresh: bool) -> dict[tuple[str, int], Path]:
    """Every (arm, seed) run, in parallel processes of one thread each (one per core).

    Small models on a few cores train faster as independent single-threaded processes than one after another
    with torch's intra-op threads, and the arms still see the same seed, data and budget.
    """
    jobs = [(arm, seed) for seed in cfg.seeds for arm in ARMS]
    workers = max(1, min(len(jobs), os.cpu_count() or 1))
    if workers == 1:
        return {job: train_arm(cfg, *job, dataset, out, fresh) for job in jobs}
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        futures = {job: pool.submit(train_arm, cfg, *job, dataset, out, fresh, 1) for job in jobs}
        return {job: future.result() for job, future in futures.items()}


def imitation_ceiling(cfg: DemoConfig, dataset: Path) -> dict:
    """What perfect perception reaches on these demonstrations (``ceiling.py``): a true-state MLP with the image
    policies' chunking, trained with the first seed and rolled out on the very episodes the arms play."""
    policy, fit = train_state_policy(dataset, steps=cfg.ceiling_steps, warmup=min(200, cfg.ceiling_steps),
                                     seed=cfg.seeds[0])
    successes, episodes, best = 0, 0, []
    for first, n in ((CALIB_SEED, cfg.calib_episodes), (LIVE_SEED, cfg.live_episodes)):
        report = evaluate_state_policy(policy, fit["env_args"], n, first)
        successes += round(report["success_rate"] * n)
        episodes += n
        best.append(report["mean_max_reward"] * n)
    print(f"   true-state policy: {successes}/{episodes} episodes", flush=True)
    return {"successes": successes, "episodes": episodes, "rate": successes / episodes,
            "ci95": list(wilson_ci(successes, episodes)), "mean_best_reward": sum(best) / episodes,
            "first_step_mse": fit["first_step_mse"], "steps": cfg.ceiling_steps, "train_seed": cfg.seeds[0]}


def audit_runs(cfg: DemoConfig, dataset: Path, checkpoints: dict) -> dict:
    """For every (arm, seed): the collapse audit (c_t first), retrieval (arms with a future head), the gradient
    interaction, and the leakage-free checkpoint selection of its run (``jepa-policy audit`` / ``protocols``)."""
    out = {}
    for (arm, seed), ckpt in checkpoints.items():
        policy = Policy.from_checkpoint(ckpt)
        demos = load_dataset(dataset, task=TASK, image_size=policy.spec.image_size)
        row = {"collapse": audit_checkpoint(policy, demos, samples=cfg.audit_samples),
               "gradients": gradient_audit(policy, demos)}
        if policy.model.cfg.has_future_token:
            row["retrieval"] = retrieval_audit(policy, demos, samples=cfg.audit_samples, pool=cfg.audit_pool)
        row["selection"] = select_checkpoint(Path(ckpt).parent.parent, ladder=cfg.selection_ladder,
                                             num_envs=cfg.num_envs, workers=cfg.workers)
        out[f"{arm} seed {seed}"] = row
        c = row["collapse"]["views"]["c_t"]
        print(f"   {arm} seed {seed}: TE32(c_t) {c['te32']:.3f}, effective rank {c['effective_rank']:.1f}; selection "
              f"picks step {row['selection']['pick']['step']}", flush=True)
    return out


def _file_digest(path: Path) -> str:
    st = path.stat()
    return _digest([str(path.resolve()), st.st_size, st.st_mtime_ns])


# ----------------------------------------------------------------------------- step 4: monitored rollouts

class Monitor:
    """The monitor service for real: uvicorn subprocess, SQLite file, admin/robot/operator keys."""

    def __init__(self, out: Path, fresh: bool):
        db = out / "monitor.db"
        if fresh or db.exists():  # a rerun re-measures its rollouts, so the monitor starts from an empty store
            for suffix in ("", "-wal", "-shm"):
                Path(str(db) + suffix).unlink(missing_ok=True)
        self.admin_key = secrets.token_urlsafe(24)
        self.server = start_server(f"sqlite:///{db}", admin_key=self.admin_key, log_path=out / "monitor.log")
        self.url = self.server.url
        self.http = httpx.Client(base_url=self.url, timeout=120.0)
        self.operator_key = self._call("POST", "/v1/keys", json={"name": "demo-operator", "role": "operator"})["key"]
        self.robot_key: str | None = None

    def _call(self, method: str, path: str, key: str | None = None, **kw):
        r = self.http.request(method, path, headers={"X-API-Key": key or self.admin_key}, **kw)
        if r.status_code >= 400:
            raise RuntimeError(f"monitor {method} {path} -> {r.status_code}: {r.text}")
        return r.json()

    def register_task(self, latent_dim: int) -> None:
        """Register PushT with the policy's latent size and create the robot's key."""
        self.robot_key = provision(self.url, self.admin_key, {TASK: latent_dim}, robot=ROBOT)

    def client(self):
        return MonitorClient(self.url, self.robot_key, robot=ROBOT)

    def calibrate(self, checkpoint: str, cfg: DemoConfig) -> dict:
        """The task's calibration from the held-out episodes, or {"error": why} when the data cannot support one
        (e.g. every held-out rollout succeeded); the run goes on and the report says so."""
        r = self.http.post("/v1/calibrations", headers={"X-API-Key": self.admin_key}, json={
            "task": TASK, "checkpoint": checkpoint, "n_bootstrap": cfg.bootstrap,
            "n_permutation": cfg.permutations, "seed": 0})
        if r.status_code in (409, 422):
            return {"error": r.json().get("detail", r.text)}
        if r.status_code >= 400:
            raise RuntimeError(f"monitor POST /v1/calibrations -> {r.status_code}: {r.text}")
        return r.json()

    def alerts(self) -> list[dict]:
        return self._call("GET", "/v1/alerts", key=self.operator_key, params={"limit": 5000})

    def episodes(self) -> list[dict]:
        return self._call("GET", "/v1/episodes", key=self.operator_key, params={"limit": 5000})

    def report(self) -> dict:
        return self._call("GET", "/v1/report", key=self.operator_key)

    def close(self) -> None:
        self.http.close()
        self.server.stop()


def run_rollouts(policy, cfg: DemoConfig, *, arm: str, seed: int, phase: str, first_seed: int, episodes: int,
                 client=None, checkpoint_id: str | None = None, bar_desc: str = "", pool=None) -> list[dict]:
    """Seeded rollouts in rounds of ``num_envs`` (in ``pool``, a persistent ``EnvPool`` of that many envs, when
    given), streaming each decision to the monitor when ``client`` is set."""
    def episode_id(rollout_seed: int) -> str:
        return f"{arm}-s{seed}-{phase}-{rollout_seed}"

    def on_decision(ev):
        eid = episode_id(ev.seed)
        if ev.kind == "prediction":
            client.decision(TASK, eid, ev.step, ev.target_step - ev.step, ev.z_hat, checkpoint=checkpoint_id,
                            held_out=phase == "calibration", group=f"seed{seed}", z_now=ev.z_now)
        else:
            client.target(eid, ev.target_step, ev.z_real)

    records = []
    with tqdm(total=episodes, desc=bar_desc or f"{arm}/{phase}", unit="ep") as bar:
        for start in range(0, episodes, cfg.num_envs):
            n = min(cfg.num_envs, episodes - start)
            report = evaluate(policy, episodes=n, seed=first_seed + start, num_envs=n, pool=pool,
                              on_decision=on_decision if client is not None else None,
                              tags={"arm": arm, "train_seed": seed, "phase": phase})
            for rec in report["records"]:
                rec["episode_id"] = episode_id(rec["seed"])
                if client is not None:
                    client.outcome(rec["episode_id"], rec["success"], held_out=phase == "calibration",
                                   group=f"seed{seed}", length=rec["length"])
                records.append(rec)
            bar.update(n)
    return records


def _first_observation(policy, seed: int) -> dict:
    env = gym.make(policy.spec.env_id, **env_kwargs_for(policy.spec, policy.env_args))
    try:
        return env.reset(seed=seed)[0]
    finally:
        env.close()


def decision_latency(policies: dict, cfg: DemoConfig) -> dict:
    """Frame-to-chunk latency of the trained EMA policies, arms interleaved in this process (Table 5 protocol).

    "jepa" is the control path (the second pass skips the future head); "jepa+monitor" also returns z_hat,
    which is what the monitored rollouts run.
    """
    obs = _first_observation(policies["jepa"], LIVE_SEED)
    variants = {"mip": (policies["mip"], False), "jepa": (policies["jepa"], False),
                "jepa+monitor": (policies["jepa"], True)}
    calls = {}
    for label, (policy, want) in variants.items():
        policy.reset()
        calls[label] = (lambda p=policy, w=want: p.predict(obs, want_future=w))
    rows = time_calls(calls, warmup=cfg.latency_warmup, iters=cfg.latency_iters)
    for label, (policy, want) in variants.items():
        passes = count_passes(policy.model, calls[label])
        rows[label].update(network_passes=max(passes.values()), passes=passes,
                           params_m=sum(p.numel() for p in policy.model.parameters()) / 1e6)
    return {"arms": rows, "warmup": cfg.latency_warmup, "iters": cfg.latency_iters,
            "threads": torch.get_num_threads()}


def rollout_frames(policy, seed: int, count: int = 5) -> list[tuple[str, np.ndarray]]:
    """A few camera frames of one JEPA rollout, for the report."""
    env = gym.make(policy.spec.env_id, **env_kwargs_for(policy.spec, policy.env_args))
    key = policy.spec.image_keys[0]
    frames, success = [], False
    try:
        obs, _ = env.reset(seed=seed)
        policy.reset()
        done, t = False, 0
        while not done:
            frames.append((t, obs[key]))
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            success |= bool(info["is_success"])
            done, t = terminated or truncated, t + 1
        frames.append((t, obs[key]))
    finally:
        env.close()
    picks = np.linspace(0, len(frames) - 1, count).round().astype(int)
    outcome = "success" if success else "failure"
    return [(f"seed {seed} step {frames[i][0]} ({outcome})" if i == picks[-1] else f"step {frames[i][0]}",
             frames[i][1]) for i in picks]


# ----------------------------------------------------------------------------- the job

# ----------------------------------------------------------------------------- step 6: failure prediction compared
# enough labelled episodes to tell a failure signal from chance, and every signal compared on them.
# Per arm of the first training seed: the embedding detectors fitted into <out>/failure/ (not beside the
# checkpoint, so the other steps act exactly as before); natural rollouts on a seed block of their own and rollouts
# per fault on the first of those seeds (each with a natural twin up to its onset); every decision carries NMSE,
# the persistence control, the whitened NMSE, STAC and the embedding scores; jepa-monitor compare on them.

FAILURE_SEED = 30_000   # rollout seeds of this step: no overlap with the calibration (10,000) and live (20,000) blocks
PREFIX = 10


def run_failure_study(cfg, dataset: Path, checkpoints: dict, arms: tuple[str, ...], out: Path) -> dict | None:
    """Record the episodes, compare every signal on them, write the files; the summary's ``failure`` entry
    (None when the mode records none)."""
    if not cfg.failure_episodes:
        return None
    seed = cfg.seeds[0]
    folder = out / "failure"
    folder.mkdir(parents=True, exist_ok=True)
    records, timing = [], {}
    demos = None
    for arm in arms:
        checkpoint = Path(checkpoints[arm, seed])
        policy = Policy.from_checkpoint(checkpoint, detectors=False)
        if demos is None:
            demos = load_dataset(dataset, task=policy.spec.name, image_size=policy.spec.image_size)
        t0 = time.perf_counter()
        path = fit_detectors(policy, checkpoint, demos, samples=cfg.failure_detector_samples, seed=0,
                             out=folder / f"{arm}_seed{seed}.detectors.npz")
        policy.detectors = load_detectors(path, checkpoint=checkpoint)
        timing[f"{arm} detectors"] = time.perf_counter() - t0
        for fault in (None, *cfg.failure_faults):
            t0 = time.perf_counter()
            n = cfg.failure_episodes if fault is None else cfg.failure_fault_episodes
            regime = fault or "natural"
            report = evaluate(policy, episodes=n, seed=FAILURE_SEED, num_envs=cfg.num_envs, workers=cfg.workers,
                              fault=None if fault is None else {"name": fault},
                              tags={"regime": regime, "arm": arm, "checkpoint": f"{arm}_seed{seed}",
                                    "train_seed": seed})
            records += report["records"]
            timing[f"{arm} {regime}"] = time.perf_counter() - t0
            print(f"   {arm} {regime}: {sum(r['success'] for r in report['records'])}/{n} successes "
                  f"({timing[f'{arm} {regime}']:.1f} s)", flush=True)
    with open(out / "failure_records.jsonl", "w") as f:
        for rec in records:
            f.write(json.dumps(rec) + "\n")
    t0 = time.perf_counter()
    episodes = [episode_of(r) for r in records]
    result = compare_signals(episodes, alpha=0.1, folds=5, prefix=PREFIX, seed=0, n_bootstrap=cfg.failure_bootstrap,
                         rule_names=("default",), views=("prefix", "whole"))
    timing["compare"] = time.perf_counter() - t0
    (out / "failure_compare.json").write_text(json.dumps(result, indent=1))
    (out / "failure_compare.md").write_text(compare_markdown(result))
    return {"seed_block": FAILURE_SEED, "train_seed": seed, "natural_episodes": cfg.failure_episodes,
            "fault_episodes": cfg.failure_fault_episodes, "faults": list(cfg.failure_faults),
            "episodes": len(records), "timing_s": {k: round(v, 1) for k, v in timing.items()},
            "result": strip_roc(result)}


def strip_roc(result: dict) -> dict:
    """The comparison without its ROC points (they stay in failure_compare.json)."""
    out = json.loads(json.dumps(result))
    for g in out["groups"].values():
        for v in g["views"].values():
            for per in v["ranking"].values():
                for r in per.values():
                    r.pop("roc", None)
    return out


def run(cfg: DemoConfig, out: Path, fresh: bool = False) -> dict:
    """Run the main job and return the summary (also written to ``out/summary.json``)."""
    out.mkdir(parents=True, exist_ok=True)
    timer = Timer()
    n_steps = (7 if cfg.audits else 6) + bool(cfg.failure_episodes)
    with timer.step(f"1/{n_steps} scripted demonstrations"):
        dataset = make_demos(cfg, out, fresh)
    with timer.step(f"2/{n_steps} training JEPA Policy and MIP (same seed, data and budget)"):
        checkpoints = train_all(cfg, dataset, out, fresh)
    with timer.step(f"3/{n_steps} imitation ceiling of these demonstrations (true-state policy, same episodes)"):
        ceiling = imitation_ceiling(cfg, dataset)

    records: list[dict] = []
    calibrations: dict[int, dict] = {}
    # The monitor server shares this machine's cores with the rollouts; torch's multi-threaded kernels then spin
    # against it (measured here: 4x slower rollouts with 2 threads than with 1), so act single-threaded.
    torch.set_num_threads(1)
    with timer.step(f"4/{n_steps} monitor service + monitored rollouts"):
        monitor, pool = Monitor(out, fresh=True), None
        try:
            print(f"   monitor at {monitor.url} (SQLite {out / 'monitor.db'})")
            for seed in cfg.seeds:
                policies = {arm: Policy.from_checkpoint(checkpoints[arm, seed]) for arm in ARMS}
                jepa = policies["jepa"]
                if monitor.robot_key is None:
                    monitor.register_task(jepa.model.future_dim)
                ckpt_id = f"jepa-seed{seed}-step{jepa.checkpoint_step}"

                if pool is None:   # one persistent rollout pool for every arm, seed and phase
                    pool = make_pool(jepa, cfg.num_envs, workers=cfg.workers)

                def monitored(phase: str, first_seed: int, episodes: int) -> list[dict]:
                    with monitor.client() as client:
                        recs = run_rollouts(jepa, cfg, arm="jepa", seed=seed, phase=phase, first_seed=first_seed,
                                            episodes=episodes, client=client, checkpoint_id=ckpt_id, pool=pool)
                        if not client.flush(timeout=120):
                            raise RuntimeError(f"the monitor client could not deliver the {phase} records")
                    return recs

                records += monitored("calibration", CALIB_SEED, cfg.calib_episodes)
                calibrations[seed] = monitor.calibrate(ckpt_id, cfg)
                records += monitored("live", LIVE_SEED, cfg.live_episodes)
                for phase, first, n in (("calibration", CALIB_SEED, cfg.calib_episodes),
                                        ("live", LIVE_SEED, cfg.live_episodes)):
                    records += run_rollouts(policies["mip"], cfg, arm="mip", seed=seed, phase=phase,
                                            first_seed=first, episodes=n, pool=pool)
            alerts, episodes, monitor_report = monitor.alerts(), monitor.episodes(), monitor.report()
        finally:
            monitor.close()
            if pool is not None:
                pool.close()
    with timer.step(f"5/{n_steps} decision latency (JEPA vs MIP, interleaved)"):
        policies = {arm: Policy.from_checkpoint(checkpoints[arm, cfg.seeds[0]]) for arm in ARMS}
        latency = decision_latency(policies, cfg)
        frames = rollout_frames(policies["jepa"], LIVE_SEED)
    failure, step = None, 6
    if cfg.failure_episodes:
        with timer.step(f"{step}/{n_steps} failure prediction compared (every signal on the same labelled "
                        "episodes, faults)"):
            failure = run_failure_study(cfg, dataset, checkpoints, ARMS, out)
        step += 1
    audits = None
    if cfg.audits:
        with timer.step(f"{step}/{n_steps} audits (collapse, retrieval, gradients) and checkpoint selection"):
            audits = audit_runs(cfg, dataset, checkpoints)
    with timer.step(f"{n_steps}/{n_steps} report"):
        summary = write_report(out, cfg=asdict(cfg), dataset=dataset, checkpoints=checkpoints, ceiling=ceiling,
                               audits=audits, records=records,
                               calibrations=calibrations, alerts=alerts, monitor_episodes=episodes,
                               monitor_report=monitor_report, latency=latency, frames=frames, failure=failure)
    summary["timing"] = {"steps_s": timer.steps, "total_s": timer.total}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(summary["text"])
    print("\nwall time per step:")
    for name, seconds in timer.steps.items():
        print(f"  {name:<60s} {seconds:7.1f} s")
    print(f"  {'total':<60s} {timer.total:7.1f} s")
    print(f"\nreport: {out / 'report.md'}")
    return summary





def demo_config(mode: str, steps: int | None = None) -> tuple[DemoConfig, str]:
    """The budget of ``mode`` with an optional training-step override, and the name of its output folder."""
    cfg = MODES[mode]
    if steps is None:
        return cfg, mode
    if steps < 1:
        raise ValueError(f"--steps must be a positive number of training steps, got {steps}")
    return replace(cfg, train_overrides={**cfg.train_overrides, "steps": steps}), f"{mode}-steps{steps}"
