"""``jepa-policy robot``: run a policy for N episodes on a robot bridge (real or simulated) and summarise them.

The bridge (``jepa_envs.real_robot``) owns the per-task chunk budget, the safety rules and the per-episode
records; this runner is the policy side. By default it is Sec. 4.8's synchronous loop (each decision completes
before its actions execute); ``--async`` uses the asynchronous executor instead (``jepa_envs.real_robot.
executor``: the next chunk is inferred while the current one executes). It tags every episode with the
evaluation manifest (checkpoint, method, seed) and reports the success rate. The policy is warmed up before
the first episode (its first call builds kernels and caches and can take seconds, longer than the bridge's
watchdog allows), and that time is reported apart. A policy is anything with ``reset()`` and
``act(obs) -> action`` (``Policy`` is one).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from jepa_envs.real_robot.executor import AsyncChunkExecutor
from jepa_envs.real_robot.proxy import RealRobotEnv
from jepa_policy.policy import Policy


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


def run_episodes(env, policy: ActingPolicy, episodes: int, seed: int = 0, manifest: dict | None = None,
                 before_episode: Callable[[int], None] | None = None, warmup: bool = True) -> dict:
    """Run ``episodes`` seeded episodes (synchronous loop); returns per-episode results and the success rate."""
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    warmup_s = warm_up(policy, env) if warmup else 0.0
    results = []
    for index in range(episodes):
        if before_episode is not None:
            before_episode(index)   # e.g. wait until the operator has set the scene up
        policy.reset()
        episode_manifest = {**(manifest or {}), "episode_index": index}
        obs, info = env.reset(seed=seed + index, options={"manifest": episode_manifest})
        steps = 0
        while True:
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            steps += 1
            if terminated or truncated:
                break
        results.append({"index": index, "seed": seed + index, "steps": steps,
                        "is_success": bool(info["is_success"]), "outcome": info.get("outcome"),
                        "interrupted": info.get("interrupted", ""), "chunks": info.get("chunks_used"),
                        "episode_manifest": info.get("episode_manifest")})
    successes = sum(r["is_success"] for r in results)
    return {"episodes": results, "successes": successes, "success_rate": successes / len(results),
            "manifest": manifest or {}, "warmup_s": warmup_s, "execution": "sync"}


def run_episodes_async(env, policy: Policy, episodes: int, seed: int = 0, manifest: dict | None = None,
                       replan_steps: int | None = None,
                       before_episode: Callable[[int], None] | None = None) -> dict:
    """Run ``episodes`` seeded episodes with the asynchronous executor (real-time chunking)."""
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    warmup_s = warm_up(policy, env)
    executor = AsyncChunkExecutor(env, lambda frames: policy.decide_from(frames).actions,
                                  history=policy.obs_steps, replan_steps=replan_steps)
    results = []
    for index in range(episodes):
        if before_episode is not None:
            before_episode(index)
        record = executor.run_episode(seed + index, {**(manifest or {}), "episode_index": index})
        results.append({"index": index, **record.summary()})
    successes = sum(r["is_success"] for r in results)
    return {"episodes": results, "successes": successes, "success_rate": successes / len(results),
            "manifest": manifest or {}, "warmup_s": warmup_s, "execution": "async",
            "replan_steps": executor.replan_steps}


def run_checkpoint_on_bridge(checkpoint: str | Path, address: str, episodes: int, seed: int = 0,
                             device: str = "cpu", method: str = "JEPA Policy", wait: bool = True,
                             asynchronous: bool = False, replan_steps: int | None = None,
                             curve_server_key: str | None = None, curve_client_key: str | None = None) -> dict:
    """Load a ``jepa-policy train`` checkpoint, connect to the bridge serving its task and run the episodes.

    ``wait``: ask the operator on stdin to set the scene up before each episode (only on a terminal).
    Raises SystemExit with the fix when the checkpoint is missing or the bridge serves another image size.
    """
    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise SystemExit(f"checkpoint {checkpoint} not found; train one with `jepa-policy train`")
    policy = Policy.from_checkpoint(checkpoint, device=device)
    env = RealRobotEnv(task=policy.spec.name, address=address, client_name=f"launcher:{checkpoint.name}",
                       curve_server_key=curve_server_key, curve_client_key=curve_client_key)
    try:
        if env.task_spec.image_size != policy.spec.image_size:
            raise SystemExit(f"the bridge serves {env.task_spec.image_size}px images, the checkpoint was trained "
                             f"on {policy.spec.image_size}px; restart the bridge with --image-size "
                             f"{policy.spec.image_size}")
        manifest = {"checkpoint": str(checkpoint.resolve()), "checkpoint_step": policy.checkpoint_step,
                    "method": method, "task": policy.spec.name}
        before = None if not wait or not sys.stdin.isatty() else (
            lambda i: input(f"Set up the scene for episode {i + 1}/{episodes}, then press Enter "))
        if asynchronous:
            return run_episodes_async(env, policy, episodes, seed, manifest, replan_steps, before_episode=before)
        return run_episodes(env, policy, episodes, seed, manifest, before_episode=before)
    finally:
        env.close()
