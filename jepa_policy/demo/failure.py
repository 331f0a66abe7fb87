"""The main job's failure-prediction step (issue 38): enough labelled episodes to tell a failure signal from
chance, and every signal compared on them (``jepa-monitor compare``).

For each arm of the first training seed: its embedding detectors (RND, PCA-kmeans, Mahalanobis) fitted on the
training set (``jepa_policy.detectors.fit_detectors``, written to ``<out>/failure/``, not beside the checkpoint, so
the other steps act exactly as before); ``failure_episodes`` natural rollouts on a seed block of their own
(``FAILURE_SEED``: the monitored and calibration blocks are untouched) and ``failure_fault_episodes`` per fault
on the first seeds of that block (each faulted episode has a natural twin up to its onset). Every decision
carries NMSE, the persistence control, the whitened NMSE, STAC and the embedding scores. The records go to
``failure_records.jsonl``, the comparison (AUROC with CI per signal x regime x view, cross-fitted detection) to
``failure_compare.json`` / ``.md``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_policy.detectors import fit_detectors, load_detectors
from jepa_policy.evaluate import evaluate
from jepa_policy.policy import Policy
from monitor_service import compare as cmp

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
            report = evaluate(policy, episodes=n, seed=FAILURE_SEED, num_envs=cfg.num_envs, workers=cfg.workers,
                              fault=None if fault is None else {"name": fault})
            regime = fault or "natural"
            for rec in report["records"]:
                rec.update(regime=regime, arm=arm, checkpoint=f"{arm}_seed{seed}", train_seed=seed)
            records += report["records"]
            timing[f"{arm} {regime}"] = time.perf_counter() - t0
            print(f"   {arm} {regime}: {sum(r['success'] for r in report['records'])}/{n} successes "
                  f"({timing[f'{arm} {regime}']:.1f} s)", flush=True)
    with open(out / "failure_records.jsonl", "w") as f:
        for rec in records:
            f.write(json.dumps(rec) + "\n")
    t0 = time.perf_counter()
    episodes = [cmp.episode_of(r) for r in records]
    result = cmp.compare(episodes, alpha=0.1, folds=5, prefix=PREFIX, seed=0, n_bootstrap=cfg.failure_bootstrap,
                         rule_names=("default",), views=("prefix", "whole"))
    timing["compare"] = time.perf_counter() - t0
    (out / "failure_compare.json").write_text(json.dumps(result, indent=1))
    (out / "failure_compare.md").write_text(cmp.markdown(result))
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


def _auc(r: dict | None) -> str:
    if not r or r.get("auroc") is None:
        return "n/a"
    return f"{r['auroc']:.3f} [{r['ci'][0]:.2f}, {r['ci'][1]:.2f}]"


def report_lines(failure: dict) -> tuple[list[str], list[str]]:
    """(Markdown lines of the report's section, console lines)."""
    result = failure["result"]
    lines = ["", f"## Failure prediction compared ({failure['episodes']} labelled episodes, "
             "`jepa-monitor compare`)", "",
             f"Per arm (training seed {failure['train_seed']}): {failure['natural_episodes']} natural rollouts on "
             f"seeds {failure['seed_block']}+ (a block of their own) and {failure['fault_episodes']} per fault "
             f"({', '.join(failure['faults']) or 'none'}) on the first of those seeds, onset at env step 30. "
             "Every signal is scored on the same episodes; negatives are the natural successes. Ranking: AUROC "
             "(95 % bootstrap CI) of the signal's mean over the view's decisions; `prefix`: the first "
             f"{result['settings']['prefix']} decisions of the episodes that reach them (PushT's failures are "
             "300-step time-outs, so a whole-episode score can rank them by length); `random` is the chance row, "
             "`nmse` ours, `nmse_persistence` the control that predicts nothing. Detection: cross-fitted in "
             f"{result['settings']['folds']} folds at alpha = {result['settings']['alpha']:g}, the service's band "
             "rule (window 5, debounce 2).", ""]
    text = []
    for view in ("prefix", "whole"):
        lines += [f"### Ranking, {view}", ""] + cmp.ranking_table(result, view)
    lines += ["### Detection: the best detector per regime, and our NMSE's", "",
              "Controls are left out of the choice; the chance row is the random signal through the same rule and "
              "calibration: a detector that does not beat it measures the episodes' lengths (PushT's failures run "
              "longest), not a failure signal.", "",
              "| arm | regime | view | best detector | TPR | false alerts on successes | balanced acc. | "
              "median delay after onset (decisions) / lead (steps) | chance row: bal. acc. | nmse band: TPR, false "
              "alerts, bal. acc. |", "|---|---|---|---|---|---|---|---|---|---|"]
    for view in ("prefix", "whole"):
        for row in cmp.best_rows(result, view, "default"):
            d = row["best_detection"]
            if d is None:
                continue
            g = result["groups"][row["group"]]
            nm = g["views"][view]["detection"]["default"]["detectors"].get("nmse band", {}).get(row["regime"])
            q = d.get("lead_steps") if row["regime"] == "natural" else d.get("delay_decisions")
            when = "-" if q is None else f"{q['median']:.3g}"
            ours = "-" if not nm or nm["balanced_accuracy"] is None else (
                f"{nm['true_alerts']}/{nm['failures']}, {nm['false_alerts']}/{nm['successes']}, "
                f"{nm['balanced_accuracy']:.3f}")
            c = row["chance_detection"]
            chance = "-" if not c or c["balanced_accuracy"] is None else f"{c['balanced_accuracy']:.3f}"
            lines.append(f"| {g['arm']} | {row['regime']} | {view} | {row['best_detector']} | "
                         f"{d['true_alerts']}/{d['failures']} | {d['false_alerts']}/{d['successes']} | "
                         f"{d['balanced_accuracy']:.3f} | {when} | {chance} | {ours} |")
    lines += ["", "Every detector's row: `failure_compare.md`; every figure: `failure_compare.json`; the records: "
              "`failure_records.jsonl` (`jepa-monitor compare failure_records.jsonl` reproduces the tables).", ""]
    for group, g in result["groups"].items():
        nat = g["views"]["prefix"]["ranking"]["natural"]
        real = {s: r for s, r in nat.items() if r.get("auroc") is not None and s not in cmp.CONTROLS}
        if not real:
            text.append(f"failure prediction {g['arm']}: no AUROC (one outcome only)")
            continue
        best = max(real, key=lambda s: real[s]["auroc"])
        text.append(f"failure prediction {g['arm']} (prefix {result['settings']['prefix']} decisions, "
                    f"{real[best]['failures']} failures / {real[best]['successes']} successes): best {best} "
                    f"{_auc(real[best])}; nmse {_auc(real.get('nmse'))}; random {_auc(nat.get('random'))}")
    return lines, text
