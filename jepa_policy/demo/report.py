"""The main job's report: figures (PNG) and a Markdown page computed from the run's stored records.

Everything here is derived from what the run recorded (rollout records, training logs, the monitor's answers);
nothing is fixed in advance. ``summarize`` is a pure function of those records so tests can recompute it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy import stats

from jepa_envs.datasets.hdf5 import demo_names
from monitor_service.offline.figures import delay_figure, roc_figure
from jepa_policy.selection import wilson_ci
from monitor_service.offline.compare import CONTROLS, best_rows, onsets_all_after_view, ranking_table
from monitor_service.offline.study import study_episode_records

EARLY_DECISIONS = 5          # paper Sec. 4.10: median NMSE of the first five decisions
MIN_CLASS_FOR_AUROC = 10     # below this many held-out successes (or failures) the AUROC is flagged as uninformative


def early_score(decisions: list[dict]) -> float | None:
    """Median NMSE of the first five decisions; None unless all five have a realized target (Sec. 4.10)."""
    first = sorted(decisions, key=lambda d: d["step"])[:EARLY_DECISIONS]
    if len(first) < EARLY_DECISIONS or any(d["nmse"] is None for d in first):
        return None
    return float(np.median([d["nmse"] for d in first]))


def _count(n: int, singular: str, plural: str) -> str:
    """'1 failure', '2 failures'."""
    return f"{n} {singular if n == 1 else plural}"


def auroc_caveat(n_success: int, n_failure: int) -> str | None:
    """A warning when the smaller class of held-out episodes is too small for the AUROC to mean much, else None.

    With m episodes in the smaller class the AUROC moves in steps of 1/m of the ranking and its bootstrap interval
    only resamples those m episodes, so it says little about how the score ranks failures in general.
    """
    m, name = min((n_success, "success"), (n_failure, "failure"))
    if m >= MIN_CLASS_FOR_AUROC:
        return None
    return (f"only {_count(m, f'held-out {name} episode', f'held-out {name} episodes')}: this AUROC and its "
            f"interval rest on {'it' if m == 1 else 'them'} and say little (at least {MIN_CLASS_FOR_AUROC} of each "
            "class are needed to read it; the paper's per-task values rest on hundreds of episodes)")


def paired_comparison(diffs: np.ndarray, n_boot: int = 20_000, seed: int = 0) -> dict:
    """Paper Sec. 4.3 statistical reading on paired differences: t interval, bootstrap, sign and Wilcoxon tests."""
    diffs = np.asarray(diffs, dtype=np.float64)
    n = diffs.size
    out = {"n": int(n), "mean": float(diffs.mean()), "differences": diffs.tolist()}
    if n >= 2 and diffs.std(ddof=1) > 0:
        half = stats.t.ppf(0.975, n - 1) * diffs.std(ddof=1) / np.sqrt(n)
        out["t_interval"] = [float(diffs.mean() - half), float(diffs.mean() + half)]
    rng = np.random.default_rng(seed)
    boot = diffs[rng.integers(0, n, size=(n_boot, n))].mean(axis=1)
    out["bootstrap_interval"] = [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))]
    nonzero = diffs[diffs != 0]
    out["sign_test_p"] = float(stats.binomtest(int((nonzero > 0).sum()), nonzero.size).pvalue) if nonzero.size else 1.0
    out["wilcoxon_p"] = float(stats.wilcoxon(nonzero).pvalue) if nonzero.size else 1.0
    return out


def _first(rows: dict) -> dict:
    return next(iter(rows.values()))


def _folds(rows: dict) -> str:
    return f"{_first(rows)['folds']} folds"


def _rate_cell(k: int, n: int, ci: list | None) -> str:
    return "n/a" if not n else f"{k}/{n} = {k / n:.2f} [{ci[0]:.2f}, {ci[1]:.2f}]"


def _quartile_cell(q: dict | None) -> str:
    return "-" if q is None else f"{q['median']:g} ({q['q1']:g}-{q['q3']:g})"


def detection_table(rows: dict) -> list[str]:
    """Markdown rows: rule x (false alerts on successes, true alerts on failures, first alert, lead)."""
    out = ["| rule | false alerts on successes [95% CI] | true alerts on failures [95% CI] | decision of the "
           "first alert, median (IQR) | lead before the end, env steps |", "|---|---|---|---|---|"]
    for name, r in rows.items():
        skipped = f" ({r['skipped_episodes']} not judged)" if r["skipped_episodes"] else ""
        out.append(f"| {name} | {_rate_cell(r['false_alerts'], r['successes'], r['false_alert_ci'])} | "
                   f"{_rate_cell(r['true_alerts'], r['failures'], r['true_alert_ci'])} | "
                   f"{_quartile_cell(r['detection_decision'])} | {_quartile_cell(r['lead_steps'])} |{skipped}")
    return out


def summarize(records: list[dict], calibrations: dict, alerts: list[dict], latency: dict,
              monitor_episodes: list[dict] = (), study: dict | None = None) -> dict:
    """Numbers of the report from the rollout records and the monitor's answers."""
    arms = sorted({r["arm"] for r in records}, key=lambda a: (a != "jepa", a))
    success = {}
    for arm in arms:
        rs = [r for r in records if r["arm"] == arm]
        k = sum(r["success"] for r in rs)
        per_seed = {}
        for seed in sorted({r["train_seed"] for r in rs}):
            srs = [r for r in rs if r["train_seed"] == seed]
            per_seed[seed] = sum(r["success"] for r in srs) / len(srs)
        success[arm] = {"rate": k / len(rs), "successes": k, "episodes": len(rs), "ci95": wilson_ci(k, len(rs)),
                        "per_seed": per_seed, "mean_length": float(np.mean([r["length"] for r in rs])),
                        "mean_best_reward": (float(np.mean([r["max_reward"] for r in rs]))
                                             if all("max_reward" in r for r in rs) else None)}

    jepa_live = [r for r in records if r["arm"] == "jepa" and r["phase"] == "live"]
    alerted = {a["episode_id"] for a in alerts}
    live_failures = [r for r in jepa_live if not r["success"]]
    live = {
        "episodes": len(jepa_live),
        "failures": len(live_failures),
        "alerts": len(alerts),
        "alerted_episodes": len(alerted),
        "alerted_failures": sum(r["episode_id"] in alerted for r in live_failures),
        "alerted_successes": sum(r["episode_id"] in alerted for r in jepa_live if r["success"]),
        "alert_notes": sorted({e["alert_note"] for e in monitor_episodes if not e["held_out"] and e["alert_note"]}),
    }
    summary = {"success": success, "calibrations": calibrations, "live": live, "latency": latency, "study": study}
    seeds = sorted({r["train_seed"] for r in records})
    if len(seeds) > 1 and {"jepa", "mip"} <= set(arms):
        diffs = np.array([success["jepa"]["per_seed"][s] - success["mip"]["per_seed"][s] for s in seeds]) * 100
        summary["paired"] = paired_comparison(diffs)
    return summary


# ----------------------------------------------------------------------------- figures

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_learning_curves(run_dirs: dict[str, Path], path: Path) -> None:
    plt = _plt()
    fig, (ax_loss, ax_eval) = plt.subplots(1, 2, figsize=(10, 3.6))
    for label, run_dir in run_dirs.items():
        rows = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines() if line.strip()]
        train_rows = [r for r in rows if "loss_act" in r or "loss" in r]
        if train_rows:
            key = "loss_act" if "loss_act" in train_rows[0] else "loss"
            ax_loss.plot([r["step"] for r in train_rows], [r[key] for r in train_rows], label=label)
        curve_file = run_dir / "eval_curve.json"
        if curve_file.exists():
            curve = json.loads(curve_file.read_text())
            ax_eval.plot([p["step"] for p in curve], [100 * p["success_rate"] for p in curve], marker="o",
                         label=label)
    ax_loss.set(xlabel="gradient step", ylabel="action loss (two-step, interval-scaled)", yscale="log",
                title="training loss")
    ax_eval.set(xlabel="gradient step", ylabel="success rate (%)", ylim=(-5, 105),
                title="periodic evaluation (EMA weights)")
    for ax in (ax_loss, ax_eval):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_roc(calibrations: dict, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.2, 4))
    ax.plot([0, 1], [0, 1], "--", color="grey", lw=1, label="chance")
    for seed, cal in calibrations.items():
        if "error" in cal:
            continue
        res = cal["result"]
        ax.plot(res["roc"]["fpr"], res["roc"]["tpr"], drawstyle="steps-post",
                label=f"seed {seed}: AUROC {res['auroc']:.3f}")
    ax.set(xlabel="false-alarm rate (successes flagged)", ylabel="failures flagged",
           title="early NMSE score, held-out rollouts")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_nmse_distributions(records: list[dict], path: Path) -> None:
    """Early scores of successes and failures (the ranking figure; the alert rules threshold another statistic)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    jepa = [r for r in records if r["arm"] == "jepa" and r.get("early_score") is not None]
    ok = [r["early_score"] for r in jepa if r["success"]]
    bad = [r["early_score"] for r in jepa if not r["success"]]
    values = np.array(ok + bad)
    if values.size:
        edges = np.geomspace(max(values.min(), 1e-6), values.max() * 1.0001 + 1e-9, 21)
        ax.hist(ok, bins=edges, alpha=0.6, label=f"successes (n={len(ok)})", color="tab:green")
        ax.hist(bad, bins=edges, alpha=0.6, label=f"failures (n={len(bad)})", color="tab:red")
        ax.set_xscale("log")
    ax.set(xlabel="early score: median NMSE of the first 5 decisions", ylabel="episodes",
           title="JEPA Policy future-consistency error")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def save_frames(frames: list[tuple[str, np.ndarray]], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, len(frames), figsize=(2.2 * len(frames), 2.5))
    for ax, (title, image) in zip(np.atleast_1d(axes), frames):
        ax.imshow(image)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- the page

def _num(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _thr(x: float) -> str:
    """An alarm threshold, four significant digits."""
    return f"{x:.4g}"


def _interval(iv: list[float] | None) -> str:
    return "n/a" if iv is None else f"[{iv[0]:+.1f}, {iv[1]:+.1f}]"


def _pct(x: float) -> str:
    return f"{100 * x:.1f}%"


def ceiling_note(success: dict, ceiling: dict) -> str:
    """How the image policies compare with what these demonstrations teach a policy that sees the true state."""
    parts = []
    for arm, s in success.items():
        lo, hi = s["ci95"]
        if hi < ceiling["ci95"][0]:
            parts.append(f"{arm} ({_pct(s['rate'])}) is below it: its interval ends before the ceiling's begins")
        elif lo > ceiling["ci95"][1]:
            parts.append(f"{arm} ({_pct(s['rate'])}) is above it")
        else:
            parts.append(f"{arm} ({_pct(s['rate'])}) cannot be told apart from it (the intervals overlap)")
    return (f"The reference is the imitation ceiling of these demonstrations, measured in this run: a 3 x 512 MLP "
            f"on the true state of the two newest steps, the image policies' chunking and padding, "
            f"{ceiling['steps']} training steps, on the same {ceiling['episodes']} episodes: "
            f"{_pct(ceiling['rate'])} [{_pct(ceiling['ci95'][0])}, {_pct(ceiling['ci95'][1])}]. "
            + "; ".join(parts) + ". A policy that sees pixels cannot be expected above what perfect perception "
            "reaches by imitating the same expert (docs/training.md, the imitation ceiling).")


def render_markdown(summary: dict, cfg: dict, figures: dict[str, str]) -> tuple[str, str]:
    """(report page, console summary)."""
    steps = cfg.get("train_overrides", {}).get("steps")
    budget = "" if steps is None else f", {steps} training steps per arm"
    lines = [f"# JEPA Policy on PushT: main job report ({cfg['mode']} mode{budget})", ""]
    text = []
    lines += ["## Success rate", "", "| arm | success | 95% CI (Wilson) | episodes | per training seed | "
              "mean best coverage | mean length |", "|---|---|---|---|---|---|---|"]
    for arm, s in summary["success"].items():
        seeds = ", ".join(f"{k}: {_pct(v)}" for k, v in s["per_seed"].items())
        lines.append(f"| {arm} | {_pct(s['rate'])} | [{_pct(s['ci95'][0])}, {_pct(s['ci95'][1])}] | "
                     f"{s['episodes']} | {seeds} | {_num(s['mean_best_reward'])} | {s['mean_length']:.0f} |")
        text.append(f"success {arm:5s}: {_pct(s['rate'])} (95% CI {_pct(s['ci95'][0])}-{_pct(s['ci95'][1])}, "
                    f"n={s['episodes']})")
    ceiling = summary.get("ceiling")
    if ceiling is not None:
        lines.append(f"| ceiling: true-state policy | {_pct(ceiling['rate'])} | [{_pct(ceiling['ci95'][0])}, "
                     f"{_pct(ceiling['ci95'][1])}] | {ceiling['episodes']} | {ceiling['train_seed']}: "
                     f"{_pct(ceiling['rate'])} | {_num(ceiling['mean_best_reward'])} | |")
        text.append(f"ceiling     : {_pct(ceiling['rate'])} (95% CI {_pct(ceiling['ci95'][0])}-"
                    f"{_pct(ceiling['ci95'][1])}, n={ceiling['episodes']}; true state, same demos and episodes)")
        lines += ["", ceiling_note(summary["success"], ceiling)]
    if "paired" in summary:
        p = summary["paired"]
        per_seed = ", ".join(f"{d:+.1f}" for d in p["differences"])
        lines += ["", "### Paired comparison over training seeds (Sec. 4.3 statistical reading)", "",
                  f"JEPA - MIP success difference per seed (points): {per_seed}; "
                  f"mean {p['mean']:+.2f}; paired t 95% interval {_interval(p.get('t_interval'))}; paired "
                  f"bootstrap interval {_interval(p['bootstrap_interval'])}; exact sign test p = "
                  f"{p['sign_test_p']:.3f}; Wilcoxon signed-rank p = {p['wilcoxon_p']:.3f}. With {p['n']} seeds no "
                  "test can reach p < 0.05 (the paper's point: the evidence is consistency, not significance)."]
        text.append(f"paired JEPA-MIP over seeds: mean {p['mean']:+.2f} points, sign p={p['sign_test_p']:.3f}")

    if (d := summary.get("demonstrations")) is not None:
        finish, task = d["finish_threshold"], d["task_threshold"]
        ends = ("" if d["final_coverage"] is None else
                f" (final coverage min {d['final_coverage'][0]:.3f}, median {d['final_coverage'][1]:.3f})")
        where = ("when the task succeeds" if finish is None  # a file written before the finish was recorded
                 else f"when the goal coverage reaches {finish:g}")
        margin = ("" if finish is None or task is None or finish <= task else
                  f", past the task's success threshold {task:g}, so that the policies learn to clear it rather than "
                  "land around it (docs/training.md)")
        lines += ["", "## Demonstrations", "",
                  f"{d['episodes']} scripted demonstrations, {d['transitions']} transitions (mean length "
                  f"{d['mean_length']:.1f} steps), kept from {d['expert_attempts']} expert attempts; each ends "
                  f"{where}{ends}{margin}."]
        text.append(f"demos: {d['episodes']} ({d['transitions']} transitions), each ending {where}")

    lat = summary["latency"]["arms"]
    lines += ["", "## Decision latency (same run, interleaved, EMA weights, batch 1)", "",
              "| arm | mean ms | p95 ms | max Hz | network passes |", "|---|---|---|---|---|"]
    for arm, row in lat.items():
        lines.append(f"| {arm} | {row['mean_ms']:.2f} | {row['p95_ms']:.2f} | {row['max_hz']:.0f} | "
                     f"{row['network_passes']} |")
    if "jepa" in lat and "mip" in lat:
        ratio = lat["jepa"]["mean_ms"] / lat["mip"]["mean_ms"]
        lines += ["", f"JEPA / MIP mean latency ratio: **{ratio:.3f}** (paper, RTX 3090 Tool Hang: 1.022)."]
        text.append(f"latency: JEPA {lat['jepa']['mean_ms']:.2f} ms, MIP {lat['mip']['mean_ms']:.2f} ms "
                    f"(ratio {ratio:.3f})")

    lines += ["", "## Future-consistency monitor (per-task calibration on held-out rollouts)", ""]
    for seed, cal in summary["calibrations"].items():
        if "error" in cal:
            lines.append(f"- seed {seed}: **no calibration**: {cal['error']}")
            text.append(f"calibration seed {seed}: none ({cal['error']})")
            continue
        r = cal["result"]
        thr, rule = cal["threshold"], r["rule"]
        lines += [
            f"- seed {seed} (checkpoint `{cal['checkpoint']}`): {r['n_failure']} failures / {r['n_success']} "
            f"successes held out. Early score (median NMSE of the first five decisions, the paper's ranking figure): "
            f"AUROC **{r['auroc']:.3f}** (95% bootstrap CI [{r['auroc_ci_low']:.3f}, "
            f"{r['auroc_ci_high']:.3f}], {r['n_bootstrap']} resamples), PR-AUC {r['average_precision']:.3f}, "
            f"permutation p = {r['permutation_p']:.4f} ({r['n_permutation']} permutations); Youden threshold "
            f"{r['youden_threshold']:.4g} (balanced accuracy in-sample {r['youden_bacc_in_sample']:.3f}, held-out "
            f"{_num(r['youden_bacc_held_out'])} by {r['held_out_method']}).",
            f"  Alert rule **{cal['rule']}** (window {rule['params']['window']}, debounce {rule['params']['debounce']}): "
            f"threshold {_thr(thr)}, so at most {r['alpha']:g} of successful episodes of this checkpoint raise any "
            f"alert ({rule['note']}).",
        ]
        text.append(f"AUROC seed {seed}: {r['auroc']:.3f} [{r['auroc_ci_low']:.3f}, {r['auroc_ci_high']:.3f}], "
                    f"permutation p={r['permutation_p']:.4f}; {cal['rule']} rule threshold {_thr(thr)}")
        if (caveat := auroc_caveat(r["n_success"], r["n_failure"])) is not None:
            lines.append(f"  **Caveat:** {caveat}.")
            text.append(f"  caveat: {caveat}")
        if r.get("detection"):
            lines += ["", f"  Cross-fitted detection on these held-out episodes ({_folds(r['detection'])}):", ""]
            lines += ["  " + row for row in detection_table(r["detection"])]
        controls = r.get("controls", {})
        if controls:
            lines += ["", "  Controls (Sec. 4.10): " + "; ".join(
                f"{name} AUROC " + ("n/a (" + c["reason"] + ")" if c["auroc"] is None else
                                    f"{c['auroc']:.3f} [{c['ci'][0]:.3f}, {c['ci'][1]:.3f}]")
                for name, c in controls.items()) + f", beside the early score's {r['auroc']:.3f}.", ""]
    lv = summary["live"]
    calibrated = any("error" not in cal for cal in summary["calibrations"].values())
    lead = ("Live rollouts scored against that calibration" if calibrated else
            "Live rollouts (no calibration exists, so the monitor raises no alert and says so on each episode)")
    lines += ["", f"{lead}: {lv['episodes']} episodes, {lv['failures']} "
              f"failures; {_count(lv['alerts'], 'intervention alert', 'intervention alerts')} on "
              f"{_count(lv['alerted_episodes'], 'episode', 'episodes')} "
              f"({_count(lv['alerted_failures'], 'failure', 'failures')}, "
              f"{_count(lv['alerted_successes'], 'success', 'successes')})."]
    if lv.get("alert_notes"):
        lines += [f"Monitor's note on the live episodes: \"{note}\"" for note in lv["alert_notes"]]
    if summary.get("study"):
        st = summary["study"]
        lines += ["", f"### Alert rules compared on every JEPA rollout of this run ({st['episodes']} episodes: "
                  f"{st['successes']} successes, {st['failures']} failures; median "
                  f"{st['scored_decisions_per_episode']['median']:g} scored decisions per episode)", "",
                  f"`jepa-monitor study records.jsonl --where arm=jepa`: each rule calibrated at alpha = "
                  f"{_first(st['rules'])['alpha']:g} on the other folds of the same checkpoint "
                  f"({_folds(st['rules'])}). The former rule's alpha covered the early score, not its alerts.", ""]
        lines += detection_table(st["rules"])
        for name, row in st["rules"].items():
            if row["successes"]:
                text.append(f"study {name}: false alerts {row['false_alerts']}/{row['successes']} successes, "
                            f"true alerts {row['true_alerts']}/{row['failures']} failures")
    text.append(f"live: {_count(lv['alerts'], 'alert', 'alerts')} on {lv['alerted_episodes']} of {lv['episodes']} "
                f"episodes ({lv['alerted_failures']}/{lv['failures']} failures and {lv['alerted_successes']}/"
                f"{lv['episodes'] - lv['failures']} successes flagged)")

    if summary.get("failure"):
        failure_lines, failure_text = failure_report_lines(summary["failure"])
        lines += failure_lines
        text += failure_text

    if summary.get("init_selection"):
        lines += ["", "## Training starts (best-of-K, docs/training.md)", "",
                  "| run | candidate seeds | mean first-step loss over the scored steps | chosen |", "|---|---|---|---|"]
        for label, sel in summary["init_selection"].items():
            steps = f"steps {sel['score_steps'][0]}-{sel['score_steps'][1]}"
            scores = ", ".join(f"{x:.4f}" for x in sel["scores"])
            lines.append(f"| {label} | {', '.join(map(str, sel['seeds']))} | {scores} ({sel['score_on']}, {steps}) "
                         f"| {sel['chosen_seed']} |")
        text.append("training starts chosen (best-of-K): " + ", ".join(
            f"{label} -> {sel['chosen_seed']}" for label, sel in summary["init_selection"].items()))

    if summary.get("audits"):
        lines += ["", "## Audits of every checkpoint (jepa-policy audit, protocols --select)", "",
                  "| run | TE32 of c_t (eff. rank) | TE32 of E_rgb | Recall@1 / @5 (chance, p) | gradient share | "
                  "selection: pick (fresh success, 95% CI) | best / last-5 / all / last |", "|---|---|---|---|---|---|---|"]
        for run, a in summary["audits"].items():
            v = a["collapse"]["views"]
            r = a.get("retrieval", {}).get("all")
            ret = "-" if r is None else (f"{_pct(r['recall_at_1'])} / {_pct(r['recall_at_5'])} "
                                          f"({_pct(r['chance_recall_at_1'])}, p = {r['permutation_p']:.3f})")
            sel, pro = a["selection"], a["selection"]["protocols"]
            pick = sel["pick"]
            lines.append(f"| {run} | {v['c_t']['te32']:.3f} ({v['c_t']['effective_rank']:.1f}) | "
                         f"{v['e_rgb']['te32']:.3f} | {ret} | {a['gradients']['gradient_share']:.4f} | step "
                         f"{pick['step']}: {_pct(pick['fresh_success_rate'])} [{_pct(pick['ci95'][0])}, "
                         f"{_pct(pick['ci95'][1])}] on {pick['fresh_episodes']} fresh episodes"
                         f"{'' if sel['decided'] else ' (undecided)'} | {_pct(pro['best'])} / "
                         f"{_pct(pro['mean_last5'])} / {_pct(pro['mean_all'])} / {_pct(pro['last'])} |")
        lines += ["", "TE32 (Sec. 4.9): spectral energy outside the leading 32 directions of the centred "
                  "representation; below 0.05 counts as low-rank. Retrieval: does z_hat pick its own realized target "
                  "among the pool (p: label-permutation null). The selection confirms the two best periodic "
                  "evaluations on fresh seeds; best / last-5 / all / last are the training curve's protocols."]
    lines += ["", "## Figures", ""]
    for title, name in figures.items():
        lines += [f"### {title}", "", f"![{title}]({name})", ""]
    lines += ["## Files", "", "- `records.jsonl`: one line per rollout (arm, seed, phase, success, length, "
              "per-decision NMSE)", "- `summary.json`: every number above", "- `monitor.db`: the monitor's "
              "SQLite store", "- `runs/<arm>_seed<seed>/`: checkpoints, TensorBoard logs, `log.jsonl`, "
              "`eval_curve.json`"]
    if summary.get("failure"):
        lines += ["- `failure_records.jsonl`, `failure_compare.json`, `failure_compare.md`, `failure/`: the failure "
                  "prediction step's rollouts (every signal per decision), its comparison and fitted detectors"]
    lines += [""]
    return "\n".join(lines), "\n".join(["", "== summary"] + ["  " + t for t in text])


def dataset_summary(path: Path) -> dict:
    """What the demonstrations file holds: counts, lengths and where the scripted expert ended each demo.

    Each demo's ``rewards`` are its per-step rewards (PushT: the goal coverage), so the last one is the coverage
    the expert finished at.
    """
    import h5py

    with h5py.File(path, "r") as f:
        data = f["data"]
        env_args = json.loads(data.attrs["env_args"])
        demos = [data[k] for k in demo_names(data)]
        lengths = np.array([int(g.attrs["num_samples"]) for g in demos])
        final = np.array([float(g["rewards"][-1]) for g in demos if "rewards" in g])
    expert = env_args.get("expert", {})
    return {
        "episodes": len(lengths), "transitions": int(lengths.sum()), "mean_length": float(lengths.mean()),
        "task_threshold": env_args.get("env_kwargs", {}).get("success_threshold"),
        "finish_threshold": expert.get("finish_threshold"), "expert_attempts": expert.get("attempts"),
        "final_coverage": ([float(final.min()), float(np.median(final))] if len(final) else None),
    }


def write_report(out: Path, *, cfg: dict, dataset: Path, checkpoints: dict, ceiling: dict | None,
                 audits: dict | None, records: list[dict],
                 calibrations: dict, alerts: list[dict], monitor_episodes: list[dict], monitor_report: dict,
                 latency: dict, frames: list[tuple[str, np.ndarray]], failure: dict | None = None) -> dict:
    """Write records.jsonl, the figures and report.md; return the summary (with the console text)."""
    for rec in records:
        rec["early_score"] = early_score(rec["decisions"]) if rec["arm"] == "jepa" else None
    with open(out / "records.jsonl", "w") as f:
        for rec in records:
            f.write(json.dumps(rec) + "\n")
    # the rule's settings of the run's calibration (the service's defaults when none could be made)
    cal = next((c["result"] for c in calibrations.values() if "error" not in c), None)
    rule = cal["rule"]["params"] if cal else {"window": 5, "debounce": 2, "clear_ratio": 0.8}
    study = study_episode_records([r for r in records if r["arm"] == "jepa"], cal["alpha"] if cal else 0.1,
                                  rule["window"], rule["debounce"], rule["clear_ratio"])
    summary = summarize(records, calibrations, alerts, latency, monitor_episodes, study)
    summary["demonstrations"] = dataset_summary(dataset)
    summary["ceiling"] = ceiling
    summary["audits"] = audits
    summary["failure"] = failure
    run_dirs = {f"{arm} seed {seed}": Path(p).parent.parent for (arm, seed), p in checkpoints.items()}
    starts = {label: json.loads((d / "init_selection.json").read_text()) for label, d in run_dirs.items()
              if (d / "init_selection.json").exists()}
    if starts:
        summary["init_selection"] = starts
    figures = {"Learning curves": "learning_curves.png", "ROC of the early NMSE score": "roc.png",
               "NMSE distributions": "nmse_distributions.png", "Rollout frames": "frames.png"}
    plot_learning_curves(run_dirs, out / figures["Learning curves"])
    plot_roc(calibrations, out / figures["ROC of the early NMSE score"])
    plot_nmse_distributions(records, out / figures["NMSE distributions"])
    save_frames(frames, out / figures["Rollout frames"])
    if failure is not None:
        full = json.loads((out / "failure_compare.json").read_text())   # with the ROC points
        figures["ROC of every failure signal (natural failures)"] = roc_figure(full, out / "failure_roc.png").name
        if (delay := delay_figure(full, out / "failure_delay.png")) is not None:
            figures["Alert delay after a fault's onset"] = delay.name
    page, text = render_markdown(summary, cfg, figures)
    (out / "report.md").write_text(page)
    summary.update(text=text, dataset=str(dataset), monitor_report=monitor_report,
                   monitor_episodes=len(monitor_episodes), alerts=alerts)
    return summary


# ----------------------------------------------------------------------------- failure prediction compared

def _auc_ci(r: dict | None) -> str:
    if not r or r.get("auroc") is None:
        return "n/a"
    return f"{r['auroc']:.3f} [{r['ci'][0]:.2f}, {r['ci'][1]:.2f}]"


def failure_report_lines(failure: dict) -> tuple[list[str], list[str]]:
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
        lines += [f"### Ranking, {view}", ""] + ranking_table(result, view)
    lines += ["### Detection: the best detector per regime, and our NMSE's", "",
              "Controls are left out of the choice; the chance row is the random signal through the same rule and "
              "calibration: a detector that does not beat it measures the episodes' lengths (PushT's failures run "
              "longest), not a failure signal.", "",
              "| arm | regime | view | best detector | TPR | false alerts on successes | balanced acc. | "
              "median delay after onset (decisions) / lead (steps) | chance row: bal. acc. | nmse band: TPR, false "
              "alerts, bal. acc. |", "|---|---|---|---|---|---|---|---|---|---|"]
    for view in ("prefix", "whole"):
        for row in best_rows(result, view, "default"):
            d = row["best_detection"]
            if d is None:
                continue
            g = result["groups"][row["group"]]
            if onsets_all_after_view(d):
                lines.append(f"| {g['arm']} | {row['regime']} | {view} | none can catch these: the onset comes after "
                             f"the last score known in this view in all {d['failures']} failures | | | | | | |")
                continue
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
        real = {s: r for s, r in nat.items() if r.get("auroc") is not None and s not in CONTROLS}
        if not real:
            text.append(f"failure prediction {g['arm']}: no AUROC (one outcome only)")
            continue
        best = max(real, key=lambda s: real[s]["auroc"])
        text.append(f"failure prediction {g['arm']} (prefix {result['settings']['prefix']} decisions, "
                    f"{real[best]['failures']} failures / {real[best]['successes']} successes): best {best} "
                    f"{_auc_ci(real[best])}; nmse {_auc_ci(real.get('nmse'))}; random {_auc_ci(nat.get('random'))}")
    return lines, text
