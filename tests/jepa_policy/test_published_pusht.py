"""The standard Push-T's published metrics from evaluation records: success rate with Wilson's interval, average
max reward with a bootstrap interval, the published figures beside them."""
import numpy as np
import pytest
from scipy.stats import binom

from jepa_policy.published import PUBLISHED_PUSHT, published_metrics, published_table


def _records(success, best):
    return [{"success": bool(s), "max_reward": float(b)} for s, b in zip(success, best)]


def test_metrics_are_the_means_of_the_records_with_the_published_figures_beside():
    records = _records([1, 0, 1, 1], [1.0, 0.5, 1.0, 0.9])
    m = published_metrics(records)
    assert m["episodes"] == 4 and m["success_rate"] == 0.75 and m["avg_max_reward"] == pytest.approx(0.85)
    assert m["success_ci95"][0] < 0.75 < m["success_ci95"][1]
    assert 0.5 <= m["avg_max_reward_ci95"][0] < 0.85 < m["avg_max_reward_ci95"][1] <= 1.0
    assert [(p["avg_max_reward"], p["success_rate"]) for p in m["published"]] == [(0.959, 0.638), (0.957, 0.642)]
    rows = published_table("JEPA", m, "4000 steps, 20 min CPU")
    assert rows[2].startswith("| JEPA | 4000 steps, 20 min CPU | 4 | 0.850 (") and "75.0% (" in rows[2]
    assert len(rows) == 2 + 1 + len(PUBLISHED_PUSHT)
    with pytest.raises(ValueError, match="no evaluation records"):
        published_metrics([])


def test_both_intervals_cover_the_true_values_as_often_as_95_percent_promises():
    """Fresh samples of 200 episodes (success p = 0.64, max reward uniform on [0.6, 1]): the share of intervals
    that hold the true value is not below what a 95 % interval allows (binomial lower bound at 0.001)."""
    rng = np.random.default_rng(12345)
    trials, n, p, mean = 200, 200, 0.64, 0.8
    held = {"success": 0, "reward": 0}
    for t in range(trials):
        m = published_metrics(_records(rng.random(n) < p, rng.uniform(0.6, 1.0, n)), resamples=1000, seed=t)
        held["success"] += m["success_ci95"][0] <= p <= m["success_ci95"][1]
        held["reward"] += m["avg_max_reward_ci95"][0] <= mean <= m["avg_max_reward_ci95"][1]
    floor = binom.ppf(0.001, trials, 0.95)
    assert held["success"] >= floor and held["reward"] >= floor, (held, floor)
