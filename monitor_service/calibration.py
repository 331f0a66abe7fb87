"""One task's calibration from its held-out labelled episodes, as a pure function of their decisions.

A calibration has four parts (docs/monitor.md):
1. the early-score figures of the paper (Sec. 4.10): AUROC with a bootstrap CI, PR-AUC, permutation p, Youden
   thresholds held out across groups; the ranking figure, not an alarm;
2. the alert rule that alarms (``rules.py``): its threshold, calibrated on the successes so that at most alpha
   of new successful episodes raise any alert;
3. cross-fitted detection figures of both rules at that alpha: false-alert rate on successes and true-alert
   rate on failures with binomial intervals, detection time and lead;
4. the paper's controls: the persistence baseline z_hat = z_t and NMSE residualised on the magnitude of latent
   change (log NMSE regressed on log persistence NMSE), each with its AUROC and CI beside the main score.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from monitor_service import rules, scoring, stats
from monitor_service.signals import (RATIO, SERVICE_SIGNALS, DetectorSpec, SignalEpisode, calibrate_detector,
                                     cross_fit_detector)

ASSUMPTIONS = (
    "The false-alert guarantee P(a successful episode raises any alert) <= alpha holds in each promised length "
    "bin of the calibration (rule.regimes with promise true: episodes of lo..hi scored decisions) for new "
    "episodes exchangeable with that bin's held-out successes: the same task, checkpoint and robot set-up, scored "
    "with the same window, debounce and hysteresis. It is finite-sample split conformal over whole episodes, "
    "averaged over the calibration draw; not a per-episode failure probability. A bin with fewer held-out "
    "successes than alpha needs (rule.unpromised_lengths) carries no promise, and an alert on an episode that can "
    "still end there says so (no_promise, and its note names the bin and its count). Decisions beyond "
    "rule.calibrated_decisions are flagged beyond_calibration: no guarantee covers them."
)


@dataclass
class LabelledEpisode:
    """A held-out episode: its decisions in step order ({"step", "target_step", "nmse", "nmse_persistence",
    "scores"}, NMSE null where the target never arrived, scores the named ones sent), outcome, group and length
    (env steps) when known."""

    episode: str
    success: bool
    decisions: list[dict] = field(default_factory=list)
    group: str | None = None
    length: int | None = None

    def scores(self) -> rules.EpisodeScores:
        return rules.EpisodeScores.from_decisions(self.decisions, self.success, self.length, self.group, self.episode)

    def early(self, key: str = "nmse", n_first: int = 5) -> float | None:
        """Median of the first ``n_first`` decisions' ``key``; None unless all of them have it (Sec. 4.10). For a
        named score: of its first ``n_first`` values (a signal such as STAC has none at the first decision)."""
        ordered = sorted(self.decisions, key=lambda d: d["step"])
        values = [_value(d, key) for d in ordered]
        if key not in TARGET_TIME:
            values = [v for v in values if v is not None]
        return scoring.early_score(values, n_first)

    def signal_episode(self) -> SignalEpisode:
        """Its decisions as per-signal arrays (NaN where a decision lacks a signal); NMSE and nmse_ratio (the
        service's signals, ``SERVICE_SIGNALS``) known at t + k."""
        ordered = sorted(self.decisions, key=lambda d: d["step"])
        names = {s for s in SERVICE_SIGNALS if any(_value(d, s) is not None for d in ordered)}
        names |= {name for d in ordered for name in (d.get("scores") or {})}
        steps = np.array([d["step"] for d in ordered], dtype=np.int64)
        known = np.array([d.get("target_step") if d.get("target_step") is not None else d["step"] for d in ordered],
                         dtype=np.int64)
        scores = {name: np.array([np.nan if _value(d, name) is None else _value(d, name) for d in ordered],
                                 dtype=np.float64) for name in sorted(names)}
        return SignalEpisode(scores, self.success, steps, {s: known for s in SERVICE_SIGNALS},
                                       self.length, self.group, self.episode)


TARGET_TIME = ("nmse", "nmse_persistence", "nmse_ratio")   # per decision, known when its target arrives


def _value(decision: dict, signal: str) -> float | None:
    """A decision's NMSE (or persistence NMSE, or their ratio ``scoring.nmse_ratio``), or one of its named scores."""
    if signal == RATIO:
        return scoring.nmse_ratio_or_none(decision.get("nmse"), decision.get("nmse_persistence"))
    if signal in TARGET_TIME:
        return decision.get(signal)
    return (decision.get("scores") or {}).get(signal)


def _labels(episodes: list[LabelledEpisode]) -> np.ndarray:
    """Failure = 1, the positive class of every statistic."""
    return np.array([0 if e.success else 1 for e in episodes], dtype=np.int64)


def early_figures(episodes: list[LabelledEpisode], early_decisions: int, n_bootstrap: int, n_permutation: int,
                  seed: int, signal: str = "nmse") -> tuple[dict, int]:
    """The paper's early-score figures over the episodes whose first decisions are all scored, and how many
    episodes were left out."""
    usable = [(e, e.early(signal, early_decisions)) for e in episodes]
    usable = [(e, s) for e, s in usable if s is not None]
    scores = np.array([s for _, s in usable], dtype=np.float64)
    labels = _labels([e for e, _ in usable])
    groups = [e.group for e, _ in usable]
    if scores.size == 0:
        raise ValueError(f"no held-out episode has an outcome and {early_decisions} decisions scored by {signal}; "
                         "record held-out labelled rollouts first")
    groups_arr = None if any(g is None for g in groups) else np.array(groups, dtype=object)
    figures = stats.calibrate(scores, labels, groups_arr, n_bootstrap, n_permutation, seed).to_dict()
    return figures, len(episodes) - len(usable)


def control_figures(episodes: list[LabelledEpisode], early_decisions: int, n_bootstrap: int, seed: int) -> dict:
    """Persistence baseline and residualised NMSE (Sec. 4.10), or why they cannot be computed here."""
    persistence = [(e, e.early("nmse_persistence", early_decisions)) for e in episodes]
    persistence = [(e, s) for e, s in persistence if s is not None]
    out = {"persistence": {"auroc": None, "ci": None, "n": len(persistence),
                           "reason": "no held-out episode sent z_now (the current latent) with its first decisions"},
           "residualised": {"auroc": None, "ci": None, "n": 0, "reason": "needs the persistence scores"}}
    if not persistence:
        return out
    out["persistence"] = {**stats.auroc_with_ci(np.array([s for _, s in persistence]),
                                                _labels([e for e, _ in persistence]), n_bootstrap, seed),
                          "what": "early score of NMSE(z_t, z_{t+k}): the future predicted as the present"}
    pairs = [(d["nmse"], d["nmse_persistence"]) for e in episodes for d in e.decisions
             if d.get("nmse") is not None and d.get("nmse_persistence") is not None]
    if len(pairs) < 3:
        out["residualised"]["reason"] = "fewer than 3 decisions with both scores"
        return out
    y = np.log(np.maximum([p[0] for p in pairs], rules.LOG_FLOOR))
    x = np.log(np.maximum([p[1] for p in pairs], rules.LOG_FLOOR))
    _, a, b = stats.residualise(y, x)
    resid = []
    for e in episodes:
        values = []
        for d in sorted(e.decisions, key=lambda d: d["step"])[:early_decisions]:
            if d.get("nmse") is None or d.get("nmse_persistence") is None:
                break
            values.append(math.log(max(d["nmse"], rules.LOG_FLOOR)) - a -
                          b * math.log(max(d["nmse_persistence"], rules.LOG_FLOOR)))
        if len(values) == early_decisions:
            resid.append((e, float(np.median(values))))
    out["residualised"] = {**stats.auroc_with_ci(np.array([s for _, s in resid]), _labels([e for e, _ in resid]),
                                                 n_bootstrap, seed),
                           "fit": {"intercept": a, "slope": b, "decisions": len(pairs)},
                           "what": "early score of log NMSE minus its least-squares line on log persistence NMSE"}
    return out


def calibrate(episodes: list[LabelledEpisode], params: rules.RuleParams, alpha: float, *, folds: int = 5,
              early_decisions: int = 5, n_bootstrap: int = 10_000, n_permutation: int = 10_000, seed: int = 0,
              signals: tuple[str, ...] = ("nmse",), combination: str = "single") -> dict:
    """Every figure of one calibration (JSON-ready): the detector of ``signals`` combined by ``combination``,
    each signal's own rule and early-score ranking, cross-fitted detection, the paper's figures and controls.
    Raises ValueError with the fix when the data cannot support it: no usable early scores, one outcome class
    only, or too few successes for a signal's rule at alpha."""
    spec = DetectorSpec(tuple(signals), combination, "successes", params)
    if RATIO in spec.signals and not any(e.signal_episode().scores.get(RATIO) is not None
                                                   for e in episodes):
        raise ValueError("no held-out episode has an nmse_ratio (NMSE over the persistence NMSE): its decisions sent "
                         "no z_now; send z_now (the current latent) with each decision of the held-out episodes "
                         "(MonitorClient.decision(..., z_now=...)), then recalibrate")
    ranking = "nmse" if any(e.early("nmse", early_decisions) is not None for e in episodes) else spec.signals[0]
    figures, skipped = early_figures(episodes, early_decisions, n_bootstrap, n_permutation, seed, ranking)
    judged = [e.signal_episode() for e in episodes]
    judged = [e for e in judged if e.scores and any(np.isfinite(v).any() for v in e.scores.values())]
    detector = calibrate_detector(spec, judged, alpha, seed)
    detection = {kind: cross_fit_detector(
        judged, replace(spec, params=replace(params, kind=kind)), alpha, folds, seed) for kind in rules.RULE_KINDS}
    return {
        **figures,
        "ranking_signal": ranking,
        "alpha": alpha,
        "rule": detector.rules[spec.signals[0]].to_dict(),
        "detector": detector.to_dict(),
        "signals": signal_figures(episodes, judged, params, alpha, early_decisions, n_bootstrap, seed),
        "detection": detection,
        "controls": control_figures(episodes, early_decisions, n_bootstrap, seed),
        "assumptions": ASSUMPTIONS,
        "skipped_episodes": skipped,
        "skipped_reason": f"held-out episodes whose first {early_decisions} decisions lack a valid {ranking} score "
                          "(left out of the early-score figures only)",
        "n_bootstrap": n_bootstrap,
        "n_permutation": n_permutation,
    }


def signal_figures(episodes: list[LabelledEpisode], judged: list[SignalEpisode], params: rules.RuleParams,
                   alpha: float, early_decisions: int, n_bootstrap: int, seed: int) -> dict:
    """Per signal with data: its own rule at alpha (or why it has none) and its early score's AUROC with CI."""
    out = {}
    for signal in sorted({s for e in judged for s in e.scores}):
        entry: dict = {"rule": None, "reason": None, "early_auroc": None}
        try:
            entry["rule"] = calibrate_detector(DetectorSpec((signal,), params=params), judged,
                                                         alpha, seed).rules[signal].to_dict()
        except ValueError as exc:
            entry["reason"] = str(exc)
        early = [(e.early(signal, early_decisions), e.success) for e in episodes]
        early = [(v, ok) for v, ok in early if v is not None]
        labels = np.array([0 if ok else 1 for _, ok in early])
        if labels.size and 0 < labels.sum() < labels.size:
            entry["early_auroc"] = stats.auroc_with_ci(np.array([v for v, _ in early]), labels, n_bootstrap, seed)
        out[signal] = entry
    return out
