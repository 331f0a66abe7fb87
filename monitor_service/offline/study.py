"""``jepa-monitor study``: replay recorded episodes through each alert rule and compare them at the same alpha.

Input, one JSON object per line, either
- episode records as ``jepa-policy eval --out`` and the main job write them: {"success", "decisions":
  [{"step", "target_step", "nmse", "nmse_persistence"?}, ...], "length"?, "episode_id"?, "arm"?, "train_seed"?,
  "group"?}; or
- the monitor's own ingest records (what a robot loop posts): {"kind": "decision", "episode", "step",
  "horizon", "z_hat", "z_now"?, "checkpoint"?, "group"?}, {"kind": "target", "episode", "step", "z"},
  {"kind": "outcome", "episode", "success", "length"?}; the NMSE is computed here as the service does.

Each rule is cross-fitted (``rules.cross_fit``) within each group (checkpoint; the main job calibrates each
checkpoint on its own): false-alert rate on successes with
its 95 % interval, true-alert rate on failures, detection time and lead. The paper's early score and the former
alert rule (conformal quantile of the early score, alerting on the running median at every later decision) are
shown beside them: that rule's guarantee covers one number per episode, not the alerts it raises.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from monitor_service import rules, scoring, stats
from monitor_service.calibration import LabelledEpisode
from monitor_service.encoding import jsonl_rows
from monitor_service.offline.synthetic import mixed_length_episodes, synthetic_episodes

OLD_RULE = "early-score threshold (former rule)"


def load_episodes(path: str | Path, where: dict | None = None) -> tuple[list[LabelledEpisode], dict]:
    """Labelled episodes of a JSONL file (either layout) and counts of what was left out and why.

    ``where``: keep only episode records whose fields equal these values (e.g. {"arm": "jepa"}).
    """
    episodes, raw, skipped = [], {}, {"no outcome": 0, "no scored decision": 0, "filtered": 0}
    for n, row in jsonl_rows(path, "pass the records.jsonl of jepa-demo or jepa-policy eval",
                             "the file must hold one JSON object per line"):
        if not isinstance(row, dict):
            raise ValueError(f"{path}:{n}: expected a JSON object, got {type(row).__name__}")
        if "kind" in row:
            _collect_record(raw, row, f"{path}:{n}")
        elif "decisions" in row:
            if where and any(row.get(k) != v for k, v in where.items()):
                skipped["filtered"] += 1
                continue
            episodes.append(_from_episode_record(row, n))
        else:
            raise ValueError(f"{path}:{n}: neither an episode record (with 'decisions') nor an ingest record "
                             "(with 'kind')")
    episodes += [_from_ingest_records(eid, rec) for eid, rec in raw.items()]
    kept = []
    for e in episodes:
        if e.success is None:
            skipped["no outcome"] += 1
        elif not any(d.get("nmse") is not None for d in e.decisions):
            skipped["no scored decision"] += 1
        else:
            kept.append(e)
    return kept, skipped


def _from_episode_record(row: dict, line: int | str) -> LabelledEpisode:
    if "success" not in row:
        raise ValueError(f"record {line}: an episode record needs 'success'")
    group = row.get("group")
    if group is None and ("arm" in row or "train_seed" in row):
        group = f"{row.get('arm', '')}-seed{row.get('train_seed', '')}"
    return LabelledEpisode(str(row.get("episode_id", row.get("seed", line))), bool(row["success"]),
                           list(row["decisions"]), group, row.get("length"))


def _collect_record(raw: dict, row: dict, where: str) -> None:
    kind, eid = row.get("kind"), row.get("episode")
    if kind not in ("decision", "target", "outcome") or not isinstance(eid, str):
        raise ValueError(f"{where}: an ingest record needs kind decision|target|outcome and an episode id")
    ep = raw.setdefault(eid, {"decisions": {}, "targets": {}, "success": None, "group": None, "length": None})
    if kind == "decision":
        ep["decisions"][int(row["step"])] = row
        ep["group"] = row.get("checkpoint") or row.get("group") or ep["group"]
    elif kind == "target":
        ep["targets"][int(row["step"])] = np.asarray(row["z"], dtype=np.float32)
    else:
        ep["success"] = bool(row["success"])
        ep["length"] = row.get("length")


def _from_ingest_records(eid: str, ep: dict) -> LabelledEpisode:
    decisions = []
    for step, d in sorted(ep["decisions"].items()):
        target_step = step + int(d["horizon"])
        z = ep["targets"].get(target_step)
        z_hat = np.asarray(d["z_hat"], dtype=np.float32)
        z_now = None if d.get("z_now") is None else np.asarray(d["z_now"], dtype=np.float32)
        decisions.append({
            "step": step, "target_step": target_step,
            "nmse": None if z is None else scoring.nmse(z_hat, z),
            "nmse_persistence": None if z is None or z_now is None else scoring.nmse(z_now, z),
        })
    return LabelledEpisode(eid, ep["success"], decisions, ep["group"], ep["length"])


class EarlyScoreRule:
    """The former alert rule, for comparison only: threshold = conformal quantile of the successes' early score
    (median NMSE of the first five scored decisions); alerts when ``debounce`` consecutive running medians of a
    full ``window`` exceed it. Its guarantee covers the early score, one number per episode."""

    def __init__(self, successes: list[rules.EpisodeScores], params: rules.RuleParams, alpha: float):
        early = np.sort([float(np.median(s.nmse[:5])) for s in successes])
        rank = rules.conformal_rank(early.size, alpha)
        if early.size == 0 or rank > early.size:
            raise ValueError(f"{early.size} successes cannot support alpha={alpha}")
        self.threshold, self.params = float(early[rank - 1]), params

    def judge(self, episode: rules.EpisodeScores) -> dict:
        w = self.params.window
        full = rules.running_statistic(episode.nmse, w)[w - 1:]
        i = rules.first_alert(full, self.threshold, self.params.debounce)
        return rules.alert_timing(episode, None if i is None else i + w - 1)


def run_study(episodes: list[LabelledEpisode], params: rules.RuleParams, alpha: float, folds: int = 5,
              seed: int = 0, n_bootstrap: int = 2000) -> dict:
    """Cross-fitted detection of both rules and the former one, and the early score's AUROC."""
    scored = [e.scores() for e in episodes]
    out = {kind: rules.cross_fit(scored, rules.RuleParams(kind, params.window, params.debounce, params.clear_ratio,
                                                          params.shape),
                                 alpha, folds, seed, within_groups=True) for kind in rules.RULE_KINDS}
    out[OLD_RULE] = {"rule": {"kind": "early", "window": params.window, "debounce": params.debounce},
                     "alpha": alpha, **rules.cross_fit_with(scored, lambda t: EarlyScoreRule(t, params, alpha),
                                                             folds, seed, within_groups=True)}
    early = [(e.early(), e.success) for e in episodes]
    early = [(s, ok) for s, ok in early if s is not None]
    ranking = stats.auroc_with_ci(np.array([s for s, _ in early]), np.array([0 if ok else 1 for _, ok in early]),
                                  n_bootstrap, seed)
    lengths = [len(s.steps) for s in scored]
    return {"rules": out, "early_score_auroc": ranking, "episodes": len(episodes),
            "successes": sum(e.success for e in episodes), "failures": sum(not e.success for e in episodes),
            "scored_decisions_per_episode": {"median": float(np.median(lengths)), "max": int(max(lengths))}
            if lengths else None}


def study_episode_records(rows: list[dict], alpha: float, window: int, debounce: int, clear_ratio: float,
                          folds: int = 5, seed: int = 0) -> dict | None:
    """``run_study`` on episode records already in memory (the main job's); None when none has a scored
    decision."""
    episodes = [_from_episode_record(row, i) for i, row in enumerate(rows)]
    episodes = [e for e in episodes if any(d.get("nmse") is not None for d in e.decisions)]
    if not episodes:
        return None
    return run_study(episodes, rules.RuleParams("running", window, debounce, clear_ratio), alpha, folds, seed)


def synthetic_study(decisions: int, successes: int, failures: int, params: rules.RuleParams, alpha: float,
                    folds: int = 5, seed: int = 0) -> dict:
    """``run_study`` on a synthetic long-horizon task (``synthetic.py``): a known distribution."""
    eps = [LabelledEpisode(s.episode, bool(s.success), [
        {"step": int(st), "target_step": int(k), "nmse": float(v)} for st, k, v in zip(s.steps, s.known_at, s.nmse)
    ], "synthetic", s.end_step) for s in synthetic_episodes(successes, failures, decisions, seed)]
    return run_study(eps, params, alpha, folds, seed)


SHORT_LENGTHS = (5, 20)   # --short-share: the calibration's short successes (the first length bin)


def calibration_successes(n: int, lengths: tuple[int, int], short_share: float | None, seed: int) -> list:
    """``n`` synthetic successes (``synthetic.mixed_length_episodes``), lengths uniform in ``lengths``; with
    ``short_share``, that share of them 5-20 decisions long and the rest uniform in 21..``lengths[1]`` (mostly
    short successes, as PushT's and every quick task's)."""
    if short_share is None:
        return mixed_length_episodes(n, 0, lengths, seed=seed)
    short = round(n * short_share)
    return (mixed_length_episodes(short, 0, SHORT_LENGTHS, seed=seed)
            + mixed_length_episodes(n - short, 0, (SHORT_LENGTHS[1] + 1, lengths[1]), seed=seed + 10**6))


def length_check(draws: int = 200, fresh: int = 200, successes: int = 100, lengths: tuple[int, int] = (5, 150),
                 alphas: tuple[float, ...] = (0.05, 0.2), params: rules.RuleParams = rules.RuleParams(),
                 seed: int = 0, progress: bool = False, short_share: float | None = None,
                 promise_min: int = rules.PROMISE_MIN_SUCCESSES) -> dict:
    """False-alert rate of fresh successes per length bin, over ``draws`` calibrations on ``successes`` fresh successes
    each (``calibration_successes``: NMSE independent of the decision index; ``short_share``: that share of them
    short), fresh successes uniform in ``lengths``. The check of docs/monitor.md's per-length promise
    (``promise_min``: the successes a bin needs for one); kinds running and band. Per bin: the rate over the
    fresh successes whose bin the calibration promised (``rate``, ``ci``), and over those it did not
    (``unpromised_*``), whose alerts must all say so. ``progress``: a bar of the calibrations on stderr."""
    out = {}
    bar = tqdm(total=len(rules.RULE_KINDS) * len(alphas) * draws, desc="length check", unit="calibration",
               disable=not progress)
    for kind in rules.RULE_KINDS:
        p = rules.RuleParams(kind, params.window, params.debounce, params.clear_ratio, params.shape)
        for alpha in alphas:
            judged = []
            for d in range(draws):
                bar.update()
                rule = rules.calibrate_rule(calibration_successes(successes, lengths, short_share, seed + 2 * d),
                                            p, alpha, seed=d, regime_min=promise_min)
                promised = {r.lo: r.promise for r in rule.regimes}
                for e in mixed_length_episodes(fresh, 0, lengths, seed=seed + 2 * d + 1):
                    verdict = rule.judge(e)
                    judged.append({**verdict, "length": e.steps.size,
                                   "promised": promised.get(rules.length_bin(e.steps.size)[0], False),
                                   "flagged": bool(verdict["unpromised"])})
            kept = {b["lo"]: b for b in rules.by_length([j for j in judged if j["promised"]])}
            bins = []
            for b in rules.by_length(judged):
                lone = [j for j in judged if not j["promised"] and rules.length_bin(j["length"])[0] == b["lo"]]
                row = kept.get(b["lo"], {"lo": b["lo"], "hi": b["hi"], "alerts": 0, "episodes": 0, "rate": None,
                                         "ci": None})
                bins.append({**row, "unpromised_episodes": len(lone),
                             "unpromised_alerts": sum(j["alerted"] for j in lone),
                             "unpromised_alerts_flagged": sum(j["alerted"] and j["flagged"] for j in lone)})
            out[f"{kind}, alpha {alpha:g}"] = bins
    bar.close()
    return {"draws": draws, "fresh_per_draw": fresh, "calibration_successes": successes, "lengths": list(lengths),
            "short_share": short_share, "promise_min": promise_min, "shape": params.shape, "rules": out}


def length_table(check: dict) -> str:
    """One row per rule and alpha: the false-alert rate in each length bin where the calibration promised it
    (and, where it did not, the share of fresh successes of that length so judged and their alerts' rate)."""
    rows = next(iter(check["rules"].values()))
    labels = [f"{max(b['lo'], check['lengths'][0])}-{min(b['hi'], check['lengths'][1])} decisions" for b in rows]
    head = "".join(f"{label:>24}" for label in labels)
    lines = [f"  {'rule, alpha':<22}{head}"]
    for name, bins in check["rules"].items():
        cells = []
        for b in bins:
            cell = "-" if b["rate"] is None else f"{b['rate']:.3f}"
            if b["unpromised_episodes"]:
                n = b["unpromised_episodes"]
                cell += (f" (np {n / (n + b['episodes']):.0%}: {b['unpromised_alerts'] / n:.2f}"
                         + ("" if b["unpromised_alerts_flagged"] == b["unpromised_alerts"] else " UNFLAGGED") + ")")
            cells.append(f"{cell:>24}")
        lines.append(f"  {name:<22}" + "".join(cells))
    mix = ("" if check.get("short_share") is None else
           f" ({check['short_share']:.0%} of them {SHORT_LENGTHS[0]}-{SHORT_LENGTHS[1]} decisions long)")
    lines.append(f"  false alerts of fresh successes in the bins the calibration promised; np: the share of fresh "
                 f"successes whose bin it did not promise (too few calibration successes that long), and their "
                 f"alert rate, every alert flagged as without promise; {check['draws']} calibrations on "
                 f"{check['calibration_successes']} successes{mix}, {check['fresh_per_draw']} fresh successes "
                 f"each; threshold shape {check['shape']}; a promise needs {check['promise_min']} successes of a "
                 "bin (and alpha's minimum)")
    return "\n".join(lines)


def _rate(k, n, ci) -> str:
    if not n:
        return "n/a"
    return f"{k}/{n} = {k / n:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]"


def _quart(q: dict | None) -> str:
    return "-" if q is None else f"{q['median']:g} ({q['q1']:g}-{q['q3']:g})"


def study_table(detection: dict) -> str:
    """One row per rule: false-alert rate on successes, true-alert rate on failures, detection time, lead."""
    header = (f"  {'rule':<38}{'false alerts on successes [95% CI]':<36}{'true alerts on failures [95% CI]':<36}"
              f"{'decision of 1st alert':<24}{'lead, env steps':<16}")
    lines = [header]
    for name, r in detection.items():
        label = name if name == OLD_RULE else f"{name} (window {r['rule']['window']}, debounce {r['rule']['debounce']})"
        lines.append(f"  {label:<38}{_rate(r['false_alerts'], r['successes'], r['false_alert_ci']):<36}"
                     f"{_rate(r['true_alerts'], r['failures'], r['true_alert_ci']):<36}"
                     f"{_quart(r['detection_decision']):<24}{_quart(r['lead_steps']):<16}")
        per_length = r.get("false_alerts_by_length")
        if per_length:
            lines.append(f"  {'':<38}false alerts by length: " + ", ".join(
                f"{b['lo']}-{b['hi'] if b['hi'] < 10**9 else ''} decisions {b['alerts']}/{b['episodes']}"
                for b in per_length)
                + (f"; alerts beyond the calibrated length: {r['alerts_beyond_calibration']}"
                   if r.get("alerts_beyond_calibration") else "")
                + (f"; false alerts on lengths without a promise: "
                   f"{r['false_alerts_unpromised']}" if r.get("false_alerts_unpromised") else ""))
    first = next(iter(detection.values()))
    lines.append(f"  cross-fitted: {first['folds']} folds; alpha = {first['alpha']}; "
                 "decision of the 1st alert as median (quartiles)")
    return "\n".join(lines)
