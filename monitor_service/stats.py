"""Calibration statistics of the early score, as pure functions (paper Sec. 4.10).

Failure is the positive class (label 1); a higher score means more risk. Every function takes one task's
episodes: raw NMSE scales differ across tasks, so pooling them destroys the ranking (Simpson-type effect).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.stats import rankdata
from sklearn.metrics import roc_curve

_CHUNK = 1000  # resamples evaluated per vectorised block; bounds memory at _CHUNK x n_episodes


def _check(scores: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels)
    if scores.ndim != 1 or scores.shape != labels.shape:
        raise ValueError(f"scores and labels must be 1-D of equal length, got {scores.shape} and {labels.shape}")
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores contain NaN or inf; drop episodes without a valid early score first")
    if not np.all((labels == 0) | (labels == 1)):
        raise ValueError("labels must be 0 (success) or 1 (failure)")
    labels = labels.astype(np.int64)
    if labels.sum() == 0 or labels.sum() == labels.size:
        raise ValueError(
            f"need both successes and failures, got {int(labels.sum())} failures of {labels.size} episodes; "
            "record more held-out episodes with outcomes"
        )
    return scores, labels


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve: P(failure score > success score) + 0.5 P(tie) (Mann-Whitney U / n1 n0)."""
    scores, labels = _check(scores, labels)
    n1 = int(labels.sum())
    n0 = labels.size - n1
    ranks = rankdata(scores)
    return float((ranks[labels == 1].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """PR-AUC as average precision: sum over thresholds of (R_k - R_{k-1}) P_k, ties grouped (step rule)."""
    scores, labels = _check(scores, labels)
    order = np.argsort(-scores, kind="mergesort")
    s, y = scores[order], labels[order]
    last_of_tie = np.r_[np.nonzero(np.diff(s))[0], s.size - 1]
    tp = np.cumsum(y)[last_of_tie]
    n_pred = last_of_tie + 1
    precision = tp / n_pred
    recall = tp / y.sum()
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def _auroc_from_positive_rank_sums(rank_sums: np.ndarray, n1: int, n0: int) -> np.ndarray:
    return (rank_sums - n1 * (n1 + 1) / 2) / (n1 * n0)


def _stratified_bootstrap_aurocs(signals: list[np.ndarray], labels: np.ndarray, n_resamples: int,
                                 seed: int) -> np.ndarray:
    """AUROC of each signal on ``n_resamples`` stratified resamples of the episodes, shape (signals, resamples).

    Each resample draws the failures from the failures and the successes from the successes with replacement
    (both classes kept at the data's sizes); every signal is read on the same resampled episodes."""
    rng = np.random.default_rng(seed)
    pos, neg = np.flatnonzero(labels == 1), np.flatnonzero(labels == 0)
    n1, n0 = pos.size, neg.size
    out = np.empty((len(signals), n_resamples))
    for start in range(0, n_resamples, _CHUNK):
        m = min(_CHUNK, n_resamples - start)
        idx = np.concatenate([pos[rng.integers(0, n1, size=(m, n1))], neg[rng.integers(0, n0, size=(m, n0))]], axis=1)
        for i, values in enumerate(signals):
            ranks = rankdata(values[idx], axis=1)
            out[i, start : start + m] = _auroc_from_positive_rank_sums(ranks[:, :n1].sum(axis=1), n1, n0)
    return out


def _percentile_interval(values: np.ndarray, level: float) -> tuple[float, float]:
    tail = (1.0 - level) / 2 * 100
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def bootstrap_auroc_ci(
    scores: np.ndarray, labels: np.ndarray, n_resamples: int = 10_000, seed: int = 0, level: float = 0.95
) -> tuple[float, float]:
    """Stratified episode-level percentile bootstrap CI of the AUROC (``_stratified_bootstrap_aurocs``): every
    resample keeps both classes and the class sizes of the data."""
    scores, labels = _check(scores, labels)
    return _percentile_interval(_stratified_bootstrap_aurocs([scores], labels, n_resamples, seed)[0], level)


def paired_auroc_difference(
    a: np.ndarray, b: np.ndarray, labels: np.ndarray, n_resamples: int = 10_000, seed: int = 0, level: float = 0.95
) -> dict:
    """AUROC(a) - AUROC(b) of two signals on the same episodes, with a paired, stratified percentile-bootstrap CI.

    Each resample draws the same failures and the same successes for both signals (with replacement, within each
    class), so the episodes' shared difficulty cancels and the interval is about the signals, not the sample.
    """
    a, labels = _check(a, labels)
    b, _ = _check(b, labels)
    auc_a, auc_b = _stratified_bootstrap_aurocs([a, b], labels, n_resamples, seed)
    low, high = _percentile_interval(auc_a - auc_b, level)
    return {"difference": auroc(a, labels) - auroc(b, labels), "ci": [low, high],
            "n": int(labels.size), "n_failure": int(labels.sum())}


def permutation_p_value(scores: np.ndarray, labels: np.ndarray, n_resamples: int = 10_000, seed: int = 0) -> float:
    """Two-sided label-permutation p-value of the AUROC against chance 0.5.

    p = (1 + #{|AUROC_perm - 0.5| >= |AUROC_obs - 0.5|}) / (1 + n_resamples), the add-one estimate that is never 0.
    """
    scores, labels = _check(scores, labels)
    n1 = int(labels.sum())
    n0 = labels.size - n1
    ranks = rankdata(scores)
    observed = abs(_auroc_from_positive_rank_sums(ranks[labels == 1].sum(), n1, n0) - 0.5)
    rng = np.random.default_rng(seed)
    hits = 0
    for start in range(0, n_resamples, _CHUNK):
        b = min(_CHUNK, n_resamples - start)
        perm = rng.permuted(np.broadcast_to(ranks, (b, ranks.size)), axis=1)
        stat = np.abs(_auroc_from_positive_rank_sums(perm[:, :n1].sum(axis=1), n1, n0) - 0.5)
        hits += int(np.sum(stat >= observed - 1e-12))
    return (1 + hits) / (1 + n_resamples)


def roc_points(scores: np.ndarray, labels: np.ndarray) -> dict[str, list[float]]:
    """ROC curve (false-positive rate, true-positive rate, threshold); alarm when score >= threshold."""
    scores, labels = _check(scores, labels)
    fpr, tpr, thr = roc_curve(labels, scores, drop_intermediate=False)
    # sklearn's first threshold is +inf ("alarm never"); JSON cannot carry inf, so mark it as None.
    return {
        "fpr": fpr.tolist(),
        "tpr": tpr.tolist(),
        "threshold": [None if not np.isfinite(t) else float(t) for t in thr],
    }


def balanced_accuracy(scores: np.ndarray, labels: np.ndarray, threshold: float) -> float:
    """Mean of the true-positive and true-negative rates when failures are predicted for score >= threshold."""
    scores, labels = _check(scores, labels)
    pred = scores >= threshold
    tpr = np.mean(pred[labels == 1])
    tnr = np.mean(~pred[labels == 0])
    return float((tpr + tnr) / 2)


def youden_threshold(scores: np.ndarray, labels: np.ndarray) -> float:
    """Threshold maximising Youden's J = TPR - FPR over the observed scores (ties: the lowest such threshold)."""
    scores, labels = _check(scores, labels)
    fpr, tpr, thr = roc_curve(labels, scores, drop_intermediate=False)
    finite = np.isfinite(thr)
    j = (tpr - fpr)[finite]
    return float(thr[finite][int(np.argmax(j))])


def held_out_balanced_accuracy(
    scores: np.ndarray, labels: np.ndarray, groups: np.ndarray | None = None, seed: int = 0
) -> tuple[float | None, str]:
    """Balanced accuracy of Youden thresholds chosen on other data than they are scored on.

    With ``groups`` (e.g. the training seed of the checkpoint) and at least two groups: leave-one-group-out, the
    paper's "held out across seeds". Otherwise a stratified two-fold split of the episodes (seeded). Each
    held-out part is thresholded by the Youden threshold of the rest; the balanced accuracy is taken over the
    pooled held-out predictions. Returns (value or None when no split has both classes on both sides, method).
    """
    scores, labels = _check(scores, labels)
    if groups is not None and len(set(groups)) >= 2:
        groups = np.asarray(groups, dtype=object)
        folds = [groups == g for g in sorted(set(groups), key=str)]
        method = f"leave-one-group-out over {len(folds)} groups"
    else:
        rng = np.random.default_rng(seed)
        fold_of = np.empty(labels.size, dtype=np.int64)
        for cls in (0, 1):
            idx = np.flatnonzero(labels == cls)
            fold_of[rng.permutation(idx)] = np.arange(idx.size) % 2
        folds = [fold_of == 0, fold_of == 1]
        method = "stratified 2-fold split of episodes"
    pred = np.zeros(labels.size, dtype=bool)
    used = np.zeros(labels.size, dtype=bool)
    for test in folds:
        train = ~test
        if len(set(labels[train])) < 2 or not test.any():
            continue
        thr = youden_threshold(scores[train], labels[train])
        pred[test] = scores[test] >= thr
        used |= test
    if not used.any() or len(set(labels[used])) < 2:
        return None, method + " (no split had both classes; not computable)"
    y, p = labels[used], pred[used]
    return float((np.mean(p[y == 1]) + np.mean(~p[y == 0])) / 2), method


@dataclass
class Calibration:
    """All per-task figures of Sec. 4.10 for one set of labelled held-out episodes."""

    n_success: int
    n_failure: int
    auroc: float
    auroc_ci_low: float
    auroc_ci_high: float
    average_precision: float
    permutation_p: float
    youden_threshold: float
    youden_bacc_in_sample: float
    youden_bacc_held_out: float | None
    held_out_method: str
    roc: dict = field(default_factory=dict)
    histogram: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


def score_histogram(scores: np.ndarray, labels: np.ndarray, bins: int = 20) -> dict[str, list[float]]:
    """Shared-edge histograms of success and failure scores (log-spaced: NMSE is positive and skewed)."""
    scores = np.asarray(scores, dtype=np.float64)
    positive = scores[scores > 0]
    if positive.size and positive.max() > positive.min():
        edges = np.geomspace(positive.min(), positive.max(), bins + 1)
    else:
        lo = float(scores.min()) if scores.size else 0.0
        edges = np.linspace(lo, lo + 1.0, bins + 1)
    clipped = np.clip(scores, edges[0], edges[-1])
    return {
        "edges": edges.tolist(),
        "success": np.histogram(clipped[labels == 0], edges)[0].tolist(),
        "failure": np.histogram(clipped[labels == 1], edges)[0].tolist(),
    }


def auroc_with_ci(scores: np.ndarray, labels: np.ndarray, n_bootstrap: int = 10_000, seed: int = 0) -> dict:
    """AUROC and its bootstrap 95 % CI, or the reason it cannot be computed (a class missing)."""
    try:
        scores, labels = _check(scores, labels)
    except ValueError as exc:
        return {"auroc": None, "ci": None, "n": int(np.size(labels)), "reason": str(exc)}
    return {"auroc": auroc(scores, labels), "ci": list(bootstrap_auroc_ci(scores, labels, n_bootstrap, seed)),
            "n": int(labels.size), "n_failure": int(labels.sum())}


def residualise(y: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Residuals of the least-squares line y = a + b x, with (a, b)."""
    y, x = np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64)
    if y.shape != x.shape or y.ndim != 1 or y.size < 3:
        raise ValueError(f"need two 1-D arrays of equal length >= 3, got {y.shape} and {x.shape}")
    b, a = np.polyfit(x, y, 1)
    return y - (a + b * x), float(a), float(b)


def calibrate(
    scores: np.ndarray,
    labels: np.ndarray,
    groups: np.ndarray | None = None,
    n_bootstrap: int = 10_000,
    n_permutation: int = 10_000,
    seed: int = 0,
) -> Calibration:
    """Compute one task's calibration from early scores and outcomes (failure = 1)."""
    scores, labels = _check(scores, labels)
    low, high = bootstrap_auroc_ci(scores, labels, n_bootstrap, seed)
    thr = youden_threshold(scores, labels)
    bacc_out, method = held_out_balanced_accuracy(scores, labels, groups, seed)
    return Calibration(
        n_success=int((labels == 0).sum()),
        n_failure=int(labels.sum()),
        auroc=auroc(scores, labels),
        auroc_ci_low=low,
        auroc_ci_high=high,
        average_precision=average_precision(scores, labels),
        permutation_p=permutation_p_value(scores, labels, n_permutation, seed),
        youden_threshold=thr,
        youden_bacc_in_sample=balanced_accuracy(scores, labels, thr),
        youden_bacc_held_out=bacc_out,
        held_out_method=method,
        roc=roc_points(scores, labels),
        histogram=score_histogram(scores, labels),
    )
