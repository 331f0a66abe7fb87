"""The standard Push-T's published metrics, computed from our evaluation records and printed beside the published
figures.

gym-pusht's reward is ``clip(coverage / 0.95, 0, 1)``; LeRobot's evaluation reports the success rate (coverage >
0.95) and ``avg_max_reward``, the mean over episodes of each episode's maximum reward (the "average max overlap"
of the papers, with the overlap normalised by 0.95 and capped at 1). Our records carry both per episode
(``success``, ``max_reward``), so the same two numbers come out, with 95 % intervals: Wilson's for the success
rate, a percentile bootstrap (seeded) for the mean of the maxima.
"""
from __future__ import annotations

import numpy as np

from jepa_policy.selection import wilson_ci

# (source, average max reward, success rate, episodes, what was trained)
PUBLISHED_PUSHT = (
    ("LeRobot diffusion_pusht", 0.959, 0.638, 500, "200k steps, 7 h on an RTX 3090"),
    ("Diffusion Policy (original code)", 0.957, 0.642, 500, "published figure"),
)
PUBLISHED_TASKS = ("PushTStandard",)


def published_metrics(records: list[dict], resamples: int = 10_000, seed: int = 0) -> dict:
    """Success rate and average max reward of ``records`` (each with ``success`` and ``max_reward``) with 95 %
    intervals, and the published figures to read them against."""
    if not records:
        raise ValueError("no evaluation records: run at least one episode")
    success = np.array([bool(r["success"]) for r in records])
    best = np.array([float(r["max_reward"]) for r in records])
    rng = np.random.default_rng(seed)
    means = best[rng.integers(0, len(best), (resamples, len(best)))].mean(axis=1)
    k, n = int(success.sum()), len(records)
    return {
        "episodes": n,
        "success_rate": k / n, "success_ci95": list(wilson_ci(k, n)),
        "avg_max_reward": float(best.mean()),
        "avg_max_reward_ci95": [float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))],
        "published": [{"source": s, "avg_max_reward": r, "success_rate": p, "episodes": e, "trained": t}
                      for s, r, p, e, t in PUBLISHED_PUSHT],
    }


def published_table(name: str, metrics: dict, budget: str) -> list[str]:
    """Markdown rows: ours (with intervals and budget) beside the published figures."""
    lo, hi = metrics["success_ci95"]
    rlo, rhi = metrics["avg_max_reward_ci95"]
    rows = ["| policy | trained | episodes | average max reward (95 % CI) | success > 0.95 (95 % CI) |",
            "|---|---|---|---|---|",
            f"| {name} | {budget} | {metrics['episodes']} | {metrics['avg_max_reward']:.3f} ({rlo:.3f}-{rhi:.3f}) | "
            f"{metrics['success_rate']:.1%} ({lo:.1%}-{hi:.1%}) |"]
    for p in metrics["published"]:
        rows.append(f"| {p['source']} | {p['trained']} | {p['episodes']} | {p['avg_max_reward']:.3f} | "
                    f"{p['success_rate']:.1%} |")
    return rows
