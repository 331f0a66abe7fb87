"""Leakage-free checkpoint selection (the rule of the paper's code), beside the four protocols of Table 6.

"Best of 30 evaluations" reports the maximum of noisy estimates chosen on the very episodes it is measured on,
so it is biased upwards. The rule here keeps choosing and measuring apart:
1. candidates: the two checkpoints with the highest success in the training run's periodic evaluations (the
   selection seeds, ``eval_seed``...);
2. confirmation on fresh seeds that no training-time evaluation used: both candidates play the same episodes;
   a paired bootstrap of the per-episode success difference decides between them when its 95 % interval
   excludes 0; while it does not, both play more fresh episodes (32 -> 64 -> 128 by default);
3. the reported number is the pick's success on those fresh episodes, with its Wilson interval.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from jepa_policy.evaluate import evaluate, make_pool, reporting_protocols
from jepa_policy.policy import Policy

FRESH_SEED = 1_000_000   # far from the training-time evaluation seeds (100,000 + episodes)
LADDER = (32, 64, 128)


def wilson_ci(successes: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return float("nan"), float("nan")
    ci = binomtest(successes, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def paired_bootstrap(a: np.ndarray, b: np.ndarray, n_resamples: int = 10_000, seed: int = 0) -> dict:
    """Mean of a - b over paired episodes and its percentile-bootstrap 95 % interval (episodes resampled)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise ValueError(f"need two equally long, non-empty outcome vectors, got {a.shape} and {b.shape}")
    diff = a - b
    idx = np.random.default_rng(seed).integers(0, diff.size, size=(n_resamples, diff.size))
    boot = diff[idx].mean(axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    return {"mean": float(diff.mean()), "ci95": [float(low), float(high)], "episodes": int(diff.size)}


def eval_snapshots(run_dir: Path) -> dict[int, Path]:
    """The EMA weights kept at each periodic evaluation (``keep_eval_checkpoints``), by step."""
    return {int(p.stem.removeprefix("eval_step")): p for p in (run_dir / "checkpoints").glob("eval_step*.pt")}


def select_checkpoint(run_dir: str | Path, fresh_seed: int = FRESH_SEED, ladder: tuple[int, ...] = LADDER,
                      num_envs: int = 4, max_steps: int | None = None, device: str = "cpu", seed: int = 0,
                      workers: int | None = 0) -> dict:
    """Apply the rule of the module docstring to a training run folder; returns the pick and the evidence."""
    run_dir = Path(run_dir)
    curve_path = run_dir / "eval_curve.json"
    if not curve_path.is_file():
        raise FileNotFoundError(f"{curve_path} does not exist; train with eval_every > 0 to record an evaluation curve")
    curve = json.loads(curve_path.read_text())
    snapshots = eval_snapshots(run_dir)
    ranked = sorted((p for p in curve if p["step"] in snapshots), key=lambda p: (-p["success_rate"], -p["step"]))
    if len(ranked) < 2:
        raise ValueError(f"{run_dir} keeps {len(snapshots)} evaluation checkpoint(s); selection needs two. Train with "
                         "keep_eval_checkpoints (the default) and at least two periodic evaluations")
    if list(ladder) != sorted(ladder) or ladder[0] < 1:
        raise ValueError(f"the episode ladder must increase from >= 1, got {ladder}")
    candidates = [p["step"] for p in ranked[:2]]
    policies = {s: Policy.from_checkpoint(snapshots[s], device=device) for s in candidates}
    outcomes: dict[int, list[bool]] = {s: [] for s in candidates}
    decision = None
    # one persistent rollout pool for both candidates and every rung (``workers`` processes; 0: in this one)
    with make_pool(policies[candidates[0]], min(num_envs, ladder[0]), workers=workers, max_steps=max_steps) as pool:
        for total in ladder:
            have = len(outcomes[candidates[0]])
            for s in candidates:   # the same fresh episodes for both: a paired comparison
                report = evaluate(policies[s], episodes=total - have, seed=fresh_seed + have, pool=pool)
                outcomes[s] += [bool(r["success"]) for r in report["records"]]
            decision = paired_bootstrap(np.array(outcomes[candidates[0]]), np.array(outcomes[candidates[1]]),
                                        seed=seed)
            if decision["ci95"][0] > 0 or decision["ci95"][1] < 0:
                break
    decided = decision["ci95"][0] > 0 or decision["ci95"][1] < 0
    rates = {s: float(np.mean(outcomes[s])) for s in candidates}
    pick = max(candidates, key=lambda s: (rates[s], s))
    k, n = int(np.sum(outcomes[pick])), len(outcomes[pick])
    return {
        "run": str(run_dir),
        "candidates": [{"step": s, "selection_success_rate": next(p["success_rate"] for p in curve if p["step"] == s),
                        "fresh_success_rate": rates[s]} for s in candidates],
        "selection_seed": json.loads((run_dir / "train_config.json").read_text()).get("eval_seed")
        if (run_dir / "train_config.json").is_file() else None,
        "fresh_seed": fresh_seed,
        "difference_first_minus_second": decision,
        "decided": decided,
        "pick": {"step": pick, "fresh_success_rate": k / n, "fresh_episodes": n, "ci95": list(wilson_ci(k, n)),
                 "why": "the paired difference excludes 0" if decided else
                        f"undecided after {n} fresh episodes: the one with the higher fresh success"},
        "protocols": reporting_protocols(curve),
    }
