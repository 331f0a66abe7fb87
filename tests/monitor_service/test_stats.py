"""Calibration statistics against scikit-learn and scipy references and constructed cases (paper Sec. 4.10)."""
import itertools

import numpy as np
import pytest
from scipy.stats import mannwhitneyu
from sklearn.metrics import average_precision_score, balanced_accuracy_score, roc_auc_score, roc_curve

from monitor_service import stats


@pytest.fixture
def data():
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 2, 240)
    scores = np.round(rng.normal(size=240) + 0.6 * labels, 1)  # rounding makes ties, the hard case
    return scores, labels


def test_auroc_matches_sklearn_and_mann_whitney(data):
    scores, labels = data
    assert stats.auroc(scores, labels) == pytest.approx(roc_auc_score(labels, scores), abs=1e-12)
    u = mannwhitneyu(scores[labels == 1], scores[labels == 0]).statistic
    assert stats.auroc(scores, labels) == pytest.approx(u / (labels.sum() * (labels == 0).sum()), abs=1e-12)


def test_average_precision_matches_sklearn(data):
    scores, labels = data
    assert stats.average_precision(scores, labels) == pytest.approx(average_precision_score(labels, scores), abs=1e-12)
    no_ties = scores + np.random.default_rng(0).normal(scale=1e-6, size=scores.size)
    assert stats.average_precision(no_ties, labels) == pytest.approx(average_precision_score(labels, no_ties),
                                                                     abs=1e-12)


def test_roc_points_match_sklearn(data):
    scores, labels = data
    roc = stats.roc_points(scores, labels)
    fpr, tpr, _ = roc_curve(labels, scores, drop_intermediate=False)
    np.testing.assert_allclose(roc["fpr"], fpr)
    np.testing.assert_allclose(roc["tpr"], tpr)
    assert roc["threshold"][0] is None  # "never alarm" point, +inf in sklearn


def test_youden_threshold_maximises_j_and_balanced_accuracy_matches_sklearn(data):
    scores, labels = data
    thr = stats.youden_threshold(scores, labels)
    fpr, tpr, thresholds = roc_curve(labels, scores)
    assert thr in thresholds
    j_best = np.max(tpr - fpr)
    pred = (scores >= thr).astype(int)
    assert stats.balanced_accuracy(scores, labels, thr) == pytest.approx(balanced_accuracy_score(labels, pred))
    assert stats.balanced_accuracy(scores, labels, thr) == pytest.approx((1 + j_best) / 2)


def test_permutation_p_agrees_with_exact_mann_whitney():
    rng = np.random.default_rng(1)
    pos = rng.normal(0.8, 1, 9)
    neg = rng.normal(0.0, 1, 11)
    scores = np.r_[pos, neg]
    labels = np.r_[np.ones(9, int), np.zeros(11, int)]
    exact = mannwhitneyu(pos, neg, method="exact").pvalue  # symmetric null: equals the |AUROC - 0.5| tail
    p = stats.permutation_p_value(scores, labels, n_resamples=20_000, seed=0)
    assert p == pytest.approx(exact, abs=0.01)


def test_permutation_p_small_exhaustive_case():
    scores = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    labels = np.array([0, 0, 0, 1, 1, 1])
    # Exact: of the C(6,3)=20 labelings, AUROC is 1 or 0 for one each: two-sided p = 2/20 = 0.1.
    combos = list(itertools.combinations(range(6), 3))
    extreme = sum(1 for c in combos if abs(stats.auroc(scores, np.isin(range(6), c).astype(int)) - 0.5) >= 0.5)
    assert extreme / len(combos) == pytest.approx(0.1)
    assert stats.permutation_p_value(scores, labels, 20_000, seed=1) == pytest.approx(0.1, abs=0.01)


def test_permutation_p_is_never_zero_and_seedable(data):
    scores, labels = data
    p1 = stats.permutation_p_value(scores, labels, 1000, seed=5)
    assert p1 == stats.permutation_p_value(scores, labels, 1000, seed=5)
    assert p1 >= 1 / 1001


def test_bootstrap_ci_constructed_cases():
    # Perfect separation: every stratified resample still separates, so the CI is [1, 1].
    scores = np.r_[np.linspace(2, 3, 20), np.linspace(0, 1, 30)]
    labels = np.r_[np.ones(20, int), np.zeros(30, int)]
    assert stats.bootstrap_auroc_ci(scores, labels, 2000, seed=0) == (1.0, 1.0)
    # Reference: the same stratified percentile bootstrap written as a plain loop over sklearn.
    rng = np.random.default_rng(4)
    labels = rng.integers(0, 2, 60)
    scores = rng.normal(size=60) + labels
    low, high = stats.bootstrap_auroc_ci(scores, labels, 2000, seed=11)
    ref_rng = np.random.default_rng(11)
    pos, neg = scores[labels == 1], scores[labels == 0]
    ref = []
    for _ in range(2):  # the implementation draws in chunks of 1000 resamples: positives then negatives
        ip = ref_rng.integers(0, pos.size, size=(1000, pos.size))
        ineg = ref_rng.integers(0, neg.size, size=(1000, neg.size))
        for a, b in zip(ip, ineg):
            ref.append(roc_auc_score(np.r_[np.ones(pos.size), np.zeros(neg.size)], np.r_[pos[a], neg[b]]))
    assert (low, high) == pytest.approx(tuple(np.percentile(ref, [2.5, 97.5])), abs=1e-12)
    assert low < stats.auroc(scores, labels) < high


def test_held_out_balanced_accuracy_leave_one_group_out():
    rng = np.random.default_rng(2)
    labels = np.tile([0, 0, 1], 30)
    scores = rng.normal(size=90) + 2 * labels
    groups = np.repeat(["seed0", "seed1", "seed2"], 30)
    value, method = stats.held_out_balanced_accuracy(scores, labels, groups)
    assert "leave-one-group-out over 3 groups" == method
    # Reference: threshold from the two other seeds, scored on the third, pooled.
    pred = np.zeros(90, bool)
    for g in ["seed0", "seed1", "seed2"]:
        test = groups == g
        pred[test] = scores[test] >= stats.youden_threshold(scores[~test], labels[~test])
    assert value == pytest.approx(balanced_accuracy_score(labels, pred))
    value2, method2 = stats.held_out_balanced_accuracy(scores, labels, None, seed=0)
    assert method2.startswith("stratified 2-fold") and 0.5 < value2 <= 1.0


def test_bad_inputs_raise_with_fix():
    with pytest.raises(ValueError, match="both successes and failures"):
        stats.auroc(np.array([1.0, 2.0]), np.array([0, 0]))
    with pytest.raises(ValueError, match="NaN"):
        stats.auroc(np.array([1.0, np.nan]), np.array([0, 1]))
    with pytest.raises(ValueError, match="equal length"):
        stats.auroc(np.array([1.0, 2.0]), np.array([0, 1, 1]))


def test_simpson_two_tasks_pooled_chance_per_task_good():
    """The paper's Simpson-type effect: per-task ranking is good, pooled raw scores are at chance."""
    rng = np.random.default_rng(0)
    # Task A: low error scale, mostly failures; task B: high scale, mostly successes.
    a_labels = np.r_[np.ones(60, int), np.zeros(20, int)]
    a_scores = np.where(a_labels == 1, rng.normal(0.30, 0.03, 80), rng.normal(0.22, 0.03, 80))
    b_labels = np.r_[np.ones(20, int), np.zeros(60, int)]
    b_scores = np.where(b_labels == 1, rng.normal(0.95, 0.09, 80), rng.normal(0.70, 0.09, 80))
    assert stats.auroc(a_scores, a_labels) > 0.9
    assert stats.auroc(b_scores, b_labels) > 0.9
    pooled = stats.auroc(np.r_[a_scores, b_scores], np.r_[a_labels, b_labels])
    low, high = stats.bootstrap_auroc_ci(np.r_[a_scores, b_scores], np.r_[a_labels, b_labels], 2000)
    assert low < 0.5 < high or pooled < 0.5, pooled


def test_calibrate_bundles_everything(data):
    scores, labels = data
    cal = stats.calibrate(np.abs(scores) + 0.01, labels, n_bootstrap=500, n_permutation=500)
    d = cal.to_dict()
    assert d["auroc"] == pytest.approx(roc_auc_score(labels, np.abs(scores)))
    assert d["n_success"] + d["n_failure"] == labels.size
    assert d["auroc_ci_low"] <= d["auroc"] <= d["auroc_ci_high"]
    assert len(d["histogram"]["success"]) == len(d["histogram"]["edges"]) - 1
    assert sum(d["histogram"]["success"]) == d["n_success"]
    assert sum(d["histogram"]["failure"]) == d["n_failure"]


def test_auroc_with_ci_and_residualise():
    rng = np.random.default_rng(3)
    labels = np.r_[np.zeros(40, int), np.ones(20, int)]
    scores = rng.normal(size=60) + labels
    out = stats.auroc_with_ci(scores, labels, n_bootstrap=500, seed=0)
    assert out["auroc"] == pytest.approx(roc_auc_score(labels, scores))
    assert out["ci"][0] <= out["auroc"] <= out["ci"][1] and out["n"] == 60 and out["n_failure"] == 20
    missing = stats.auroc_with_ci(scores[:40], labels[:40])
    assert missing["auroc"] is None and "both successes and failures" in missing["reason"]
    x = rng.normal(size=50)
    y = 2.0 + 3.0 * x + rng.normal(scale=0.1, size=50)
    resid, a, b = stats.residualise(y, x)
    ref = np.polyfit(x, y, 1)
    assert (b, a) == pytest.approx(tuple(ref)) and abs(resid.mean()) < 1e-9 and abs(np.dot(resid, x)) < 1e-8
    with pytest.raises(ValueError, match="equal length"):
        stats.residualise(y, x[:10])


def test_paired_auroc_difference_covers_the_true_difference_and_pairing_narrows_it():
    """Two signals on the same episodes from a known law: failures shifted by d_a and d_b in two correlated
    Gaussian scores, so AUROC = Phi(d / sqrt 2) each. Over fresh samples the paired 95 % interval holds the true
    difference about 95 % of the time (within the binomial bound of the draws), its point value is the two
    AUROCs' difference, and sharing the episodes makes it much narrower than two separate intervals."""
    from scipy.stats import binom, norm

    d_a, d_b, rho, n1, n0, draws = 1.2, 0.8, 0.8, 40, 60, 200
    truth = norm.cdf(d_a / np.sqrt(2)) - norm.cdf(d_b / np.sqrt(2))
    rng = np.random.default_rng(7)
    covered, widths, separate = 0, [], []
    labels = np.r_[np.ones(n1, int), np.zeros(n0, int)]
    for k in range(draws):
        common = rng.normal(size=n1 + n0)
        a = rho * common + np.sqrt(1 - rho**2) * rng.normal(size=n1 + n0) + d_a * labels
        b = rho * common + np.sqrt(1 - rho**2) * rng.normal(size=n1 + n0) + d_b * labels
        r = stats.paired_auroc_difference(a, b, labels, n_resamples=400, seed=k)
        assert r["difference"] == pytest.approx(stats.auroc(a, labels) - stats.auroc(b, labels))
        covered += r["ci"][0] <= truth <= r["ci"][1]
        widths.append(r["ci"][1] - r["ci"][0])
        ca, cb = (stats.bootstrap_auroc_ci(x, labels, 400, k) for x in (a, b))
        separate.append((ca[1] - ca[0]) + (cb[1] - cb[0]))
    assert binom.cdf(covered, draws, 0.95) > 1e-3, f"coverage {covered}/{draws} below the promised 0.95"
    assert binom.sf(covered - 1, draws, 0.95) > 1e-3, f"coverage {covered}/{draws} suspiciously above 0.95"
    assert np.median(widths) < 0.6 * np.median(separate)
    same = stats.paired_auroc_difference(a, a, labels, n_resamples=200)
    assert same["difference"] == 0.0 and same["ci"] == [0.0, 0.0]
    with pytest.raises(ValueError):
        stats.paired_auroc_difference(a, b, np.zeros_like(labels))
