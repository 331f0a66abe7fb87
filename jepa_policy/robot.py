"""``jepa-policy robot``: run a policy for N episodes on a robot bridge (real or simulated) and summarise them.

The bridge (``jepa_robot``) owns the per-task chunk budget, the safety rules and the per-episode
records; this runner is the policy side. By default it is Sec. 4.8's synchronous loop (each decision completes
before its actions execute); ``--async`` uses the asynchronous executor instead (``jepa_envs.real_robot.
executor``: the next chunk is inferred while the current one executes). It tags every episode with the
evaluation manifest (checkpoint, method, seed) and reports the success rate. The policy is warmed up before
the first episode (its first call builds kernels and caches and can take seconds, longer than the bridge's
watchdog allows), and that time is reported apart. A policy is anything with ``reset()`` and
``act(obs) -> action`` (``Policy`` is one).

With a monitor (``--monitor-url``, ``MonitorReporter``) the synchronous loop sends every decision's z_hat, the
present latent (the persistence control) and its named failure scores (``Decision.scores``: STAC, and RND,
PCA-kmeans and Mahalanobis when the checkpoint has fitted detectors), the realized latent of each decision's
target frame, and the episode's outcome, as ``jepa-policy serve`` does.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
from tqdm import tqdm

from jepa_envs.real_robot.executor import AsyncChunkExecutor
from jepa_envs.real_robot.proxy import RealRobotEnv
from jepa_policy.policy import Policy
from monitor_service.client import MonitorClient


class ActingPolicy(Protocol):
    def reset(self) -> None: ...

    def act(self, obs: dict) -> np.ndarray: ...


def blank_observation(env) -> dict:
    """An all-zero observation of the env's observation space (images black, proprioception zero)."""
    return {key: np.zeros(space.shape, space.dtype) for key, space in env.observation_space.spaces.items()}


def warm_up(policy: ActingPolicy, env, calls: int = 2) -> float:
    """Run the policy on blank observations until its first-call costs are paid; returns the seconds spent.

    Nothing reaches the robot: the actions are thrown away and the policy is reset afterwards.
    """
    start = time.monotonic()
    obs = blank_observation(env)
    for _ in range(calls):
        policy.reset()
        policy.act(obs)
    policy.reset()
    return time.monotonic() - start


class MonitorReporter:
    """The robot loop's side of the monitor: per decision z_hat (for step + k), the present latent and the named
    scores; per target frame its realized latent; per episode the outcome (``MonitorClient``, batched, retried).

    ``scores``: which of the decision's scores to send (None: every finite one; the task must have them
    registered, ``jepa-monitor tasks add TASK --signals stac,rnd,pca_kmeans,mahalanobis``, or the monitor
    refuses the record)."""

    def __init__(self, client: MonitorClient, task: str, checkpoint: str | None = None,
                 scores: tuple[str, ...] | None = None):
        self.client, self.task, self.checkpoint, self.scores = client, task, checkpoint, scores
        self.episode = ""
        self._pending: set[int] = set()

    def start(self, episode: str) -> None:
        self.episode, self._pending = episode, set()

    def observed(self, policy: Policy, obs: dict, decided: bool) -> None:
        """After ``policy.act(obs)``: report the decision it made (``decided``) and any target frame ``obs`` is."""
        t = policy.t
        if t in self._pending:
            self._pending.discard(t)
            self.client.target(self.episode, t, policy.encode_future(obs))
        if not decided:
            return
        d = policy.last_decision
        scores = {k: v for k, v in d.scores.items() if np.isfinite(v) and (self.scores is None or k in self.scores)}
        if d.z_hat is None and not scores:
            return
        self.client.decision(self.task, self.episode, d.step, d.k if d.z_hat is not None else None, d.z_hat,
                             checkpoint=self.checkpoint, scores=scores or None,
                             z_now=policy.encode_future(obs) if d.z_hat is not None else None)
        if d.z_hat is not None:
            self._pending.add(d.target_step)

    def target_frame(self, policy: Policy, obs: dict, step: int) -> None:
        """The frame of env step ``step`` (after the last action of a loop that does not act on it)."""
        if step in self._pending:
            self._pending.discard(step)
            self.client.target(self.episode, step, policy.encode_future(obs))

    def outcome(self, success: bool, length: int) -> None:
        self.client.outcome(self.episode, success, length=length)


def run_episodes(env, policy: ActingPolicy, episodes: int, seed: int = 0, manifest: dict | None = None,
                 before_episode: Callable[[int], None] | None = None, warmup: bool = True,
                 monitor: MonitorReporter | None = None, progress: bool = False) -> dict:
    """Run ``episodes`` seeded episodes (synchronous loop); returns per-episode results and the success rate.
    ``monitor`` (a ``Policy`` then): every decision, target and outcome goes to the monitor service.
    ``progress``: a bar of the episodes on stderr."""
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    warmup_s = warm_up(policy, env) if warmup else 0.0
    results = []
    for index in tqdm(range(episodes), desc="robot", unit="episode", disable=not progress):
        if before_episode is not None:
            before_episode(index)   # e.g. wait until the operator has set the scene up
        policy.reset()
        episode_manifest = {**(manifest or {}), "episode_index": index}
        obs, info = env.reset(seed=seed + index, options={"manifest": episode_manifest})
        if monitor is not None:
            monitor.start(f"{(manifest or {}).get('run', 'robot')}-{seed + index}-{time.time_ns()}")
        steps = 0
        while True:
            before = getattr(policy, "last_decision", None)
            action = policy.act(obs)
            if monitor is not None:
                monitor.observed(policy, obs, policy.last_decision is not before)
            obs, _, terminated, truncated, info = env.step(action)
            steps += 1
            if terminated or truncated:
                break
        if monitor is not None:
            monitor.target_frame(policy, obs, steps)
            monitor.outcome(bool(info["is_success"]), steps)
        results.append({"index": index, "seed": seed + index, "steps": steps,
                        "is_success": bool(info["is_success"]), "outcome": info.get("outcome"),
                        "interrupted": info.get("interrupted", ""), "chunks": info.get("chunks_used"),
                        "episode_manifest": info.get("episode_manifest")})
    successes = sum(r["is_success"] for r in results)
    return {"episodes": results, "successes": successes, "success_rate": successes / len(results),
            "manifest": manifest or {}, "warmup_s": warmup_s, "execution": "sync"}


def run_episodes_async(env, policy: Policy, episodes: int, seed: int = 0, manifest: dict | None = None,
                       replan_steps: int | None = None,
                       before_episode: Callable[[int], None] | None = None, progress: bool = False) -> dict:
    """Run ``episodes`` seeded episodes with the asynchronous executor (real-time chunking; ``progress``: a bar
    of the episodes on stderr)."""
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    warmup_s = warm_up(policy, env)
    executor = AsyncChunkExecutor(env, lambda frames: policy.decide_from(frames).actions,
                                  history=policy.obs_steps, replan_steps=replan_steps)
    results = []
    for index in tqdm(range(episodes), desc="robot", unit="episode", disable=not progress):
        if before_episode is not None:
            before_episode(index)
        record = executor.run_episode(seed + index, {**(manifest or {}), "episode_index": index})
        results.append({"index": index, **record.summary()})
    successes = sum(r["is_success"] for r in results)
    return {"episodes": results, "successes": successes, "success_rate": successes / len(results),
            "manifest": manifest or {}, "warmup_s": warmup_s, "execution": "async",
            "replan_steps": executor.replan_steps}


BRIDGE_BACKENDS = {"SimBackend": "sim", "ARX5Backend": "arx5", "ReplayBackend": "replay"}


def image_size_refusal(address: str, welcome: dict, policy: Policy) -> str:
    """Why a bridge of another image size is refused, and the bridge command that fits the checkpoint."""
    served, size, task = welcome["spec"]["image_size"], policy.image_size, policy.spec.name
    backend = BRIDGE_BACKENDS.get(welcome.get("backend"), "sim")
    if backend == "replay":
        fix = f"replay an episode recorded at {size} px (a replayed episode keeps its recorded frames)"
    elif backend == "arx5":
        fix = f"restart it with `jepa-robot-bridge serve --backend arx5 --config CONFIG --image-size {size}`"
    else:
        fix = f"restart it with `jepa-robot-bridge serve --backend sim --task {task} --image-size {size}`"
    return (f"the bridge at {address} serves {served} px images, this checkpoint acts on {size} px (the image size "
            f"it was trained at); {fix}, keeping its other flags")


def run_checkpoint_on_bridge(checkpoint: str | Path, address: str, episodes: int, seed: int = 0,
                             device: str = "cpu", method: str = "JEPA Policy", wait: bool = True,
                             asynchronous: bool = False, replan_steps: int | None = None,
                             curve_server_key: str | None = None, curve_client_key: str | None = None,
                             monitor_url: str | None = None, monitor_key: str | None = None,
                             task_id: str | None = None, robot: str | None = None,
                             monitor_scores: tuple[str, ...] | None = None, monitor_flush_s: float = 30.0,
                             progress: bool = False) -> dict:
    """Load a ``jepa-policy train`` checkpoint, connect to the bridge serving its task and run the episodes.

    ``wait``: ask the operator on stdin to set the scene up before each episode (only on a terminal).
    ``monitor_url`` / ``monitor_key`` (a robot key): report every decision with its scores to the monitor under
    ``task_id`` (default: the checkpoint's task); ``monitor_scores``: which scores (default every finite one).
    ``progress``: a bar of the episodes on stderr.
    Raises SystemExit with the fix when the checkpoint is missing or the bridge serves another image size.
    """
    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise SystemExit(f"checkpoint {checkpoint} not found; train one with `jepa-policy train`")
    if monitor_url and not monitor_key:
        raise ValueError("--monitor-url needs --monitor-key (a robot key of the monitor service: jepa-monitor keys "
                         "create --role robot)")
    if monitor_url and asynchronous:
        raise ValueError("--monitor-url reports the synchronous loop's decisions; drop --async")
    policy = Policy.from_checkpoint(checkpoint, device=device)
    env = RealRobotEnv(task=policy.spec.name, address=address, client_name=f"launcher:{checkpoint.name}",
                       curve_server_key=curve_server_key, curve_client_key=curve_client_key)
    try:
        if env.task_spec.image_size != policy.image_size:
            raise SystemExit(image_size_refusal(address, env.welcome, policy))
        manifest = {"checkpoint": str(checkpoint.resolve()), "checkpoint_step": policy.checkpoint_step,
                    "method": method, "task": policy.spec.name}
        before = None if not wait or not sys.stdin.isatty() else (
            lambda i: input(f"Set up the scene for episode {i + 1}/{episodes}, then press Enter "))
        if asynchronous:
            return run_episodes_async(env, policy, episodes, seed, manifest, replan_steps, before_episode=before,
                                      progress=progress)
        if not monitor_url:
            return run_episodes(env, policy, episodes, seed, manifest, before_episode=before, progress=progress)
        client = MonitorClient(monitor_url, monitor_key, robot=robot)
        try:
            reporter = MonitorReporter(client, task_id or policy.spec.name,
                                       f"{checkpoint.name}@{policy.checkpoint_step}", monitor_scores)
            summary = run_episodes(env, policy, episodes, seed, manifest, before_episode=before, monitor=reporter,
                                   progress=progress)
        finally:
            delivered = client.close(timeout=monitor_flush_s)
        stats = client.stats
        summary["monitor"] = {"url": monitor_url, "task": reporter.task, "delivered": delivered,
                              "dropped": stats.dropped, "rejected": len(stats.rejected),
                              "first_rejection": ({"status": stats.rejected[0][1], "message": stats.rejected[0][2]}
                                                  if stats.rejected else None)}
        return summary
    finally:
        env.close()
