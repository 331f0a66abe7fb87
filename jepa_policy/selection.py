"""Leakage-free checkpoint selection (the rule of the paper's code), beside the four protocols of Table 6.

"Best of 30 evaluations" reports the maximum of noisy estimates chosen on the very episodes it is measured on,
so it is biased upwards. The rule here keeps choosing and measuring apart:
1. candidates: the two checkpoints with the highest success in the training run's periodic evaluations (the
   selection seeds, ``eval_seed``...);
2. confirmation on fresh seeds that no training-time evaluation used: both candidates play the same episodes;
   a paired bootstrap of the per-episode success difference decides between them when its 95 % interval
   excludes 0; while it does not, both play more fresh episodes (32 -> 64 -> 128 by default);
3. the reported number is the pick's success on a third block of seeds that neither the training-time
   evaluations nor the confirmation played (from ``REPORT_SEED``), with its Wilson interval. Reported on the
   confirmation episodes it would be biased upwards again, because the pick won there (two candidates of true
   success 0.50: 0.529 on average).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.stats import binomtest
from tqdm import tqdm

from jepa_policy.evaluate import evaluate, make_pool, reporting_protocols
from jepa_policy.policy import Policy
from jepa_policy.progress import EpisodeProgress

FRESH_SEED = 1_000_000   # far from the training-time evaluation seeds (100,000 + episodes)
REPORT_SEED = 2_000_000  # the untouched block the pick's success is reported on
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


def confirm_and_report(play: Callable[[int, int, int], list[bool]], candidates: list[int],
                       fresh_seed: int = FRESH_SEED, ladder: tuple[int, ...] = LADDER, report_seed: int = REPORT_SEED,
                       report_episodes: int | None = None, seed: int = 0) -> dict:
    """Steps 2 and 3 of the rule for two candidates, given ``play(candidate, first_seed, episodes) -> outcomes``.

    Both candidates play the same confirmation episodes from ``fresh_seed``, rung by rung of ``ladder``, until the
    paired bootstrap decides; the pick then plays ``report_episodes`` (default: the last rung) from
    ``report_seed``, and that is the success reported."""
    if len(candidates) != 2:
        raise ValueError(f"the rule compares two candidates, got {len(candidates)}")
    if list(ladder) != sorted(ladder) or ladder[0] < 1:
        raise ValueError(f"the episode ladder must increase from >= 1, got {ladder}")
    report_episodes = ladder[-1] if report_episodes is None else report_episodes
    if report_episodes < 1:
        raise ValueError(f"report_episodes must be >= 1, got {report_episodes}")
    if report_seed < fresh_seed + ladder[-1] and fresh_seed < report_seed + report_episodes:
        raise ValueError(f"the report block (seeds {report_seed}-{report_seed + report_episodes - 1}) overlaps the "
                         f"confirmation block ({fresh_seed}-{fresh_seed + ladder[-1] - 1}); pass a --report-seed "
                         "outside it")
    outcomes: dict[int, list[bool]] = {c: [] for c in candidates}
    decision = None
    for total in ladder:
        have = len(outcomes[candidates[0]])
        for c in candidates:   # the same fresh episodes for both: a paired comparison
            outcomes[c] += play(c, fresh_seed + have, total - have)
        decision = paired_bootstrap(np.array(outcomes[candidates[0]]), np.array(outcomes[candidates[1]]), seed=seed)
        if decision["ci95"][0] > 0 or decision["ci95"][1] < 0:
            break
    decided = decision["ci95"][0] > 0 or decision["ci95"][1] < 0
    rates = {c: float(np.mean(outcomes[c])) for c in candidates}
    pick = max(candidates, key=lambda c: (rates[c], c))
    reported = play(pick, report_seed, report_episodes)
    k, n = int(np.sum(reported)), len(reported)
    return {"confirmation_success_rate": rates, "confirmation_episodes": len(outcomes[pick]),
            "difference_first_minus_second": decision, "decided": decided,
            "pick": {"step": pick, "fresh_success_rate": k / n, "fresh_episodes": n, "ci95": list(wilson_ci(k, n)),
                     "report_seed": report_seed,
                     "why": "the paired difference excludes 0" if decided else
                            f"undecided after {len(outcomes[pick])} confirmation episodes: the one with the higher "
                            "success there"}}


def select_checkpoint(run_dir: str | Path, fresh_seed: int = FRESH_SEED, ladder: tuple[int, ...] = LADDER,
                      num_envs: int = 4, max_steps: int | None = None, device: str = "cpu", seed: int = 0,
                      workers: int | None = 0, report_seed: int = REPORT_SEED,
                      report_episodes: int | None = None, progress: bool = False) -> dict:
    """Apply the rule of the module docstring to a training run folder; returns the pick and the evidence. The
    pick's ``fresh_success_rate`` is measured on the report block (``report_seed``), untouched by the choice.
    ``progress``: a bar of the episodes played on stderr (their number depends on when the ladder decides)."""
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
    config = run_dir / "train_config.json"
    trained = json.loads(config.read_text()) if config.is_file() else {}
    if "eval_seed" in trained:
        first, count = int(trained["eval_seed"]), int(trained.get("eval_episodes", 0))
        for name, start, n in (("--fresh-seed", fresh_seed, ladder[-1]),
                               ("--report-seed", report_seed, report_episodes or ladder[-1])):
            if start < first + count and first < start + n:
                raise ValueError(f"{name} {start} overlaps the training-time evaluation seeds {first}-"
                                 f"{first + count - 1} of {run_dir}; pick seeds no evaluation of this run played")
    candidates = [p["step"] for p in ranked[:2]]
    policies = {s: Policy.from_checkpoint(snapshots[s], device=device) for s in candidates}
    # one persistent rollout pool for both candidates, every rung and the report (``workers`` processes; 0: here)
    with make_pool(policies[candidates[0]], min(num_envs, ladder[0]), workers=workers, max_steps=max_steps) as pool, \
            tqdm(desc="selection", unit="episode", disable=not progress) as bar:
        seen = EpisodeProgress(pool, bar)

        def play(step: int, first_seed: int, episodes: int) -> list[bool]:
            report = evaluate(policies[step], episodes=episodes, seed=first_seed, pool=seen)
            seen.finish()
            return [bool(r["success"]) for r in report["records"]]

        result = confirm_and_report(play, candidates, fresh_seed, ladder, report_seed, report_episodes, seed)
    return {
        "run": str(run_dir),
        "candidates": [{"step": s, "selection_success_rate": next(p["success_rate"] for p in curve if p["step"] == s),
                        "confirmation_success_rate": result["confirmation_success_rate"][s]} for s in candidates],
        "selection_seed": trained.get("eval_seed"),
        "fresh_seed": fresh_seed,
        "confirmation_episodes": result["confirmation_episodes"],
        "report_seed": report_seed,
        "difference_first_minus_second": result["difference_first_minus_second"],
        "decided": result["decided"],
        "pick": result["pick"],
        "protocols": reporting_protocols(curve),
    }
