"""Task launcher: run a policy for N episodes on the robot (or a simulated bridge) and summarise them.

The bridge owns the per-task chunk budget, the safety rules and the per-episode records; the launcher runs
the synchronous loop of Sec. 4.8 on the policy side (each decision completes before its actions execute),
tags every episode with the evaluation manifest (checkpoint, method, seed) and reports the success rate.
A policy is anything with ``reset()`` and ``act(obs) -> action`` (``jepa_policy.policy.Policy`` is one).
"""
from __future__ import annotations

from typing import Callable, Protocol

import numpy as np


class ActingPolicy(Protocol):
    def reset(self) -> None: ...

    def act(self, obs: dict) -> np.ndarray: ...


def run_episodes(env, policy: ActingPolicy, episodes: int, seed: int = 0, manifest: dict | None = None,
                 before_episode: Callable[[int], None] | None = None) -> dict:
    """Run ``episodes`` seeded episodes; returns per-episode results and the success rate."""
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
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
            "manifest": manifest or {}}
