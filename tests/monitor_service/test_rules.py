"""Alert rules: the episode-level false-alert guarantee on fresh episodes from a known distribution, detection of
drifting failures, the former rule's excess, and the pure pieces against brute-force references."""
import math

import numpy as np
import pytest
from scipy.stats import binom, binomtest

from monitor_service import rules
from monitor_service.alerts import AlertState, step_alert
from monitor_service.offline.study import EarlyScoreRule
from monitor_service.offline.synthetic import SyntheticTask, synthetic_episodes

ALPHA = 0.1
N_CAL = 20          # successes per calibration: running uses all 20, band fits on 10 and ranks 10
PAIRS = 500         # independent (calibration set, fresh episode) pairs per configuration
PAIRS_BY_LENGTH = 200


def exact_false_alert_rate(kind: str) -> float:
    """1 - r / (n + 1) for the conformal rank r over the n episodes the quantile is taken from."""
    n = N_CAL if kind == "running" else N_CAL - N_CAL // 2
    return 1 - rules.conformal_rank(n, ALPHA) / (n + 1)


@pytest.mark.parametrize("decisions", [6, 40, 100])
@pytest.mark.parametrize("kind", ["running", "band"])
def test_fresh_successes_alert_at_most_alpha_whatever_the_length(kind, decisions):
    """Each pair: a fresh calibration set and one fresh successful episode of the same law, so the count of
    alerted episodes is Binomial(PAIRS, p) with p = 1 - r/(n+1) <= alpha (continuous statistics)."""
    params = rules.RuleParams(kind)
    alerts = 0
    for i in range(PAIRS):
        cal = synthetic_episodes(N_CAL, 0, decisions, seed=1_000_000 * decisions + 2 * i)
        rule = rules.calibrate_rule(cal, params, ALPHA, seed=i)
        fresh = synthetic_episodes(1, 0, decisions, seed=1_000_000 * decisions + 2 * i + 1)[0]
        alerts += rule.judge(fresh)["alerted"]
    p = exact_false_alert_rate(kind)
    assert p <= ALPHA
    # not above the promise: a one-sided binomial test against alpha does not reject at 0.001
    assert binomtest(alerts, PAIRS, ALPHA, alternative="greater").pvalue > 1e-3, alerts
    # and not a rule that never fires: inside the two-sided 99.8 % binomial range of the exact rate
    assert binom.ppf(0.001, PAIRS, p) <= alerts <= binom.ppf(0.999, PAIRS, p), (alerts, p * PAIRS)


LENGTH_BINS = ((5, 20), (21, 40), (41, 80), (81, 150))


def mixed_length_successes(n: int, rng: np.random.Generator) -> list[rules.EpisodeScores]:
    """Successes of a known law: iid lognormal NMSE that does not depend on the decision index; a quarter of the
    episodes in each bin of LENGTH_BINS, their lengths uniform within it."""
    bins = np.asarray(LENGTH_BINS)[np.arange(n) % len(LENGTH_BINS)]
    lengths = rng.integers(bins[:, 0], bins[:, 1] + 1)
    out = []
    for length in lengths:
        steps = np.arange(length, dtype=np.int64) * 8
        out.append(rules.EpisodeScores(steps, np.exp(rng.normal(-2.0, 0.5, length)), steps + 4, success=True,
                                       end_step=8 * int(length)))
    return out


def one_per_bin(rng: np.random.Generator) -> list[rules.EpisodeScores]:
    out = []
    for lo, hi in LENGTH_BINS:
        length = int(rng.integers(lo, hi + 1))
        steps = np.arange(length, dtype=np.int64) * 8
        out.append(rules.EpisodeScores(steps, np.exp(rng.normal(-2.0, 0.5, length)), steps + 4, success=True))
    return out


@pytest.mark.parametrize("kind, shape, n_cal, alphas", [("running", "flat", 100, (0.05, 0.2)),
                                                       ("band", "flat", 200, (0.05, 0.2)),
                                                       ("running", "running-max", 200, (0.2,))])
def test_fresh_successes_alert_at_most_alpha_in_every_length_bin(kind, shape, n_cal, alphas):
    """Independent (calibration set, fresh success) pairs, one fresh success per length bin: per bin the number
    of alerted episodes is Binomial(PAIRS_BY_LENGTH, p) with p <= alpha (the guarantee per length regime; the
    calibration is sized so that its regimes are these bins, or nearly: band and running-max rank half of
    theirs). The former marginal rule gave 0.31 at alpha 0.2 in the 81-150 bin."""
    params = rules.RuleParams(kind, shape=shape)
    counts = {alpha: np.zeros(len(LENGTH_BINS), dtype=np.int64) for alpha in alphas}
    for i in range(PAIRS_BY_LENGTH):
        rng = np.random.default_rng([17, n_cal, i])
        cal = mixed_length_successes(n_cal, rng)
        fresh = one_per_bin(rng)
        for alpha in alphas:
            rule = rules.calibrate_rule(cal, params, alpha, seed=i)
            if kind == "running" and shape == "flat":   # all 100 rank: the regimes are the bins, so the promise
                assert [(r.lo, r.hi) for r in rule.regimes][:3] == [(1, 20), (21, 40), (41, 80)]   # is per bin
            counts[alpha] += [rule.judge(e)["alerted"] for e in fresh]
    for alpha, alerted in counts.items():
        for (lo, hi), k in zip(LENGTH_BINS, alerted):
            # not above the promise: a one-sided binomial test against alpha does not reject at 0.001
            assert binomtest(int(k), PAIRS_BY_LENGTH, alpha, alternative="greater").pvalue > 1e-3, \
                (alpha, lo, hi, k)
        # and a rule that fires: the binding (longest) bin sits near alpha, not at zero
        assert alerted[-1] >= binom.ppf(0.001, PAIRS_BY_LENGTH, alpha / 4), (alpha, alerted)


SKEWED = {((5, 20), 150), ((21, 40), 20), ((41, 80), 15), ((81, 150), 15)}   # 75 % short, few long (as PushT's)
SCARCE = {((5, 20), 150), ((21, 40), 30), ((41, 80), 15), ((81, 150), 5)}   # too few long successes for 0.1


def successes_of(counts, rng: np.random.Generator) -> list[rules.EpisodeScores]:
    """``counts`` {(lo, hi): n} successes of the known law of ``mixed_length_successes``, lengths uniform in
    their bin."""
    out = []
    for (lo, hi), n in sorted(counts):
        for length in rng.integers(lo, hi + 1, size=n):
            steps = np.arange(length, dtype=np.int64) * 8
            out.append(rules.EpisodeScores(steps, np.exp(rng.normal(-2.0, 0.5, length)), steps + 4, success=True))
    return out


@pytest.mark.parametrize("counts, kind, shape, regime_min", [(SKEWED, "running", "flat", 1),
                                                             (SKEWED, "running", "flat", 20),
                                                             (SCARCE, "running", "flat", 1),
                                                             (SKEWED, "band", "running-max", 1)])
def test_skewed_calibration_keeps_the_promise_per_length_or_says_it_has_none(counts, kind, shape, regime_min):
    """Calibrations whose successes are mostly short. Per length bin, over independent (calibration, fresh
    success) pairs: where the rule promises the bin, alerts on fresh successes of that length are
    Binomial(promised pairs, p <= alpha) (the former rule merged the scarce long bin into a 21-150 regime and
    alerted at 0.17-0.34 there at alpha 0.1); where it does not (too few calibration successes of those
    lengths: alpha's minimum, and 20 with ``regime_min`` 20), every alert on such a success says why."""
    params = rules.RuleParams(kind, shape=shape)
    for alpha in (0.1, 0.2):
        promised_alerts = {b: [0, 0] for b in LENGTH_BINS}
        unpromised_alerts = {b: [0, 0] for b in LENGTH_BINS}
        for i in range(PAIRS_BY_LENGTH):
            rng = np.random.default_rng([29, len(counts), hash(kind) % 1000, int(alpha * 10), i])
            rule = rules.calibrate_rule(successes_of(counts, rng), params, alpha, seed=i, regime_min=regime_min)
            if kind == "running" and counts is SKEWED:   # every bin holds >= 9 (0.1) or 4 (0.2); 15 < 20
                assert [(r.lo, r.promise) for r in rule.regimes] == [(1, True), (21, True), (41, regime_min == 1),
                                                                     (81, regime_min == 1)]
            if kind == "running" and counts is SCARCE and alpha == 0.1:   # 5 < 9
                assert [r.promise for r in rule.regimes] == [True, True, True, False] and \
                    [u["successes"] for u in rule.unpromised_lengths()] == [5]
            for (lo, hi), fresh in zip(LENGTH_BINS, one_per_bin(rng)):
                regime = next(r for r in rule.regimes if r.lo == rules.length_bin(fresh.n_decisions)[0])
                verdict = rule.judge(fresh)
                tally = (promised_alerts if regime.promise else unpromised_alerts)[(lo, hi)]
                tally[0] += verdict["alerted"]
                tally[1] += 1
                if verdict["alerted"]:   # flagged exactly when its length has no promise, saying how many there were
                    assert (verdict["unpromised"] == "") == regime.promise, verdict
                    assert regime.promise or f"a length with {regime.n} calibration successes" in verdict["unpromised"]
        for (lo, hi), (k, n) in promised_alerts.items():
            if n:
                assert binomtest(k, n, alpha, alternative="greater").pvalue > 1e-3, (alpha, lo, hi, k, n)
        if counts is SCARCE and kind == "running" and alpha == 0.1:
            k, n = unpromised_alerts[(81, 150)]
            assert n == PAIRS_BY_LENGTH and k > 0   # judged (at the largest promised level) and flagged, not promised


def test_running_max_shape_against_a_direct_computation():
    """q(i) = the median over fitting successes reaching index i of their running maximum (held where fewer
    than 3 reach it, non-decreasing); lambda per regime = the conformal rank of max_i min over d of log(r/q)."""
    rng = np.random.default_rng(3)
    cal = mixed_length_successes(60, rng)
    params = rules.RuleParams("running", shape="running-max")
    rule = rules.calibrate_rule(cal, params, 0.2, seed=4)   # every bin with a finite quantile promised
    fit, conf = rules.fit_split(60, 4)
    runs = [rules.running_statistic(e.nmse, 5) for e in cal]
    longest = max(runs[i].size for i in conf)
    q, last = [], None
    for i in range(longest):
        reach = [np.maximum.accumulate(runs[j])[i] for j in fit if runs[j].size > i]
        last = float(np.median(reach)) if len(reach) >= 3 else last
        q.append(last)
    q = np.maximum.accumulate(q)
    assert np.allclose(rule.shape, q)
    stats = {j: max(min(np.log(runs[j][k] / q[k]) for k in (i - 1, i)) for i in range(1, runs[j].size))
             for j in conf}
    for regime in rule.regimes:
        members = sorted(v for j, v in stats.items() if regime.lo <= runs[j].size <= regime.hi)
        assert regime.n == len(members) and regime.level == pytest.approx(members[regime.rank - 1])
        assert regime.rank == rules.conformal_rank(len(members), 0.2)
    # lambda(i): the largest level among the regimes an episode at index i can still end in
    levels = rule.levels()
    for i in range(longest):
        assert levels[i] == max(r.level for r in rule.regimes if r.hi > i)
    assert np.allclose(rule.thresholds(longest), q * np.exp(levels))
    # a minimum of 20: 30 ranked successes over four bins, none holding 20: no bin promised, each judged at the
    # quantile of all of them together
    pooled = rules.calibrate_rule(cal, params, 0.2, seed=4, regime_min=20)
    ranked = sorted(stats.values())
    assert [r.promise for r in pooled.regimes] == [False] * 4 and all(r.rank == 0 for r in pooled.regimes)
    assert all(r.level == pytest.approx(ranked[rules.conformal_rank(len(ranked), 0.2) - 1]) for r in pooled.regimes)
    assert "no promise at 1-20 decisions" in pooled.note and pooled.unpromised(0).startswith("no false-alert promise")


def test_length_regimes_one_per_bin_promised_where_enough_and_flag_beyond():
    lengths = [3] * 25 + [30] * 9 + [60] * 22 + [200] * 3
    # every bin up to the longest episode is a regime of its own; 81-160 is empty and 161-200 holds 3 (alpha 0.1
    # needs 9): neither promised, and never merged into 41-80 (whose quantile the 60-decision episodes set)
    assert [(lo, hi, idx.size, ok) for lo, hi, idx, ok in rules.length_regimes(lengths, 0.1)] == \
        [(1, 20, 25, True), (21, 40, 9, True), (41, 80, 22, True), (81, 160, 0, False), (161, 200, 3, False)]
    # alpha 0.05 needs 19: 21-40 loses its promise too
    assert [ok for *_, ok in rules.length_regimes(lengths, 0.05)] == [True, False, True, False, False]
    cal = synthetic_episodes(30, 0, 10, seed=1)
    rule = rules.calibrate_rule(cal, rules.RuleParams("running"), ALPHA)
    assert rule.calibrated_decisions == 10
    long_fail = synthetic_episodes(0, 1, 40, seed=2, task=SyntheticTask(drift=4.0))[0]
    timing = rule.judge(long_fail)
    assert timing["alerted"] and timing["beyond_calibration"] == (timing["decision_index"] >= 10)
    assert np.all(rule.thresholds(40)[10:] == rule.threshold)   # held beyond the calibrated decisions


def test_former_early_score_rule_exceeds_alpha_on_long_episodes():
    """Conformal on the early score, alerting on the running median at every later decision: far above alpha."""
    params, alerts = rules.RuleParams("running"), 0
    for i in range(200):
        cal = synthetic_episodes(N_CAL, 0, 40, seed=7_000 + 2 * i)
        fresh = synthetic_episodes(1, 0, 40, seed=7_000 + 2 * i + 1)[0]
        alerts += EarlyScoreRule(cal, params, ALPHA).judge(fresh)["alerted"]
    assert binomtest(alerts, 200, ALPHA, alternative="greater").pvalue < 1e-6, alerts
    assert alerts / 200 > 0.3


@pytest.mark.parametrize("kind, least", [("running", 0.5), ("band", 0.9)])
def test_failures_drifting_in_their_second_half_are_detected(kind, least):
    cal = synthetic_episodes(40, 0, 40, seed=11)
    rule = rules.calibrate_rule(cal, rules.RuleParams(kind), ALPHA, seed=0)
    failures = synthetic_episodes(0, 100, 40, seed=12)
    judged = [rule.judge(f) for f in failures]
    assert np.mean([j["alerted"] for j in judged]) >= least
    # the drift starts at decision 20: detections come after it, each known at its target step
    hits = [j for j in judged if j["alerted"]]
    assert np.median([j["decision_index"] for j in hits]) >= 20
    assert all(j["known_at"] == 8 * j["decision_index"] + 4 and j["lead"] == 320 - j["known_at"] for j in hits)


def test_band_follows_the_task_phase():
    """Successes whose typical error changes with the phase: the band's centre tracks it at every step."""
    task = SyntheticTask(phase_amplitude=1.0, noise_sd=0.1, episode_sd=0.0)
    band = rules.fit_band(synthetic_episodes(60, 0, 40, seed=3, task=task))
    j = np.arange(40)
    expected = task.base + task.phase_amplitude * np.sin(2 * np.pi * j / task.phase_period)
    assert band.steps == list(8 * j)
    assert np.max(np.abs(np.array(band.center) - expected)) < 0.1
    assert all(0.05 < s < 0.2 for s in band.scale)
    # a step between knots takes the knot before it; before the first, the first
    z = band.standardise(np.array([0, 9, 15, 16]), np.exp(np.array(band.center)[[0, 1, 1, 2]]))
    assert np.allclose(z, 0.0)


def test_pure_pieces_against_brute_force():
    rng = np.random.default_rng(0)
    for n in (0, 1, 4, 5, 6, 30):
        v = rng.lognormal(size=n)
        ref = np.array([np.median(v[max(0, i - 4): i + 1]) for i in range(n)])
        run = rules.running_statistic(v, 5)
        assert np.array_equal(run, ref)
        a = rules.alert_statistic(run, 2)
        if n < 2:
            assert a == -math.inf
            continue
        # A is the smallest threshold at which the episode never alerts: just below it alerts, at it not
        assert rules.first_alert(run, a, 2) is None and rules.first_alert(run, a - 1e-9, 2) is not None
        # and the service's step_alert raises at exactly the pure function's index
        state, raised = AlertState(), None
        for i, r in enumerate(run):
            state, event = step_alert(state, r, a - 1e-9, 2, 0.8 * a)
            if event == "raise":
                raised = i
                break
        assert raised == rules.first_alert(run, a - 1e-9, 2)


def test_conformal_rank_and_minimum_successes():
    assert rules.conformal_rank(9, 0.1) == 9 and rules.conformal_rank(8, 0.1) == 9
    assert rules.min_conformal_episodes(0.1) == 9 and rules.min_conformal_episodes(0.05) == 19
    assert rules.min_successes(0.1, rules.RuleParams("running")) == 9
    assert rules.min_successes(0.1, rules.RuleParams("band")) == 17
    assert rules.min_successes(0.1, rules.RuleParams("running", shape="running-max")) == 17
    with pytest.raises(ValueError, match="alpha"):
        rules.conformal_rank(10, 1.5)


def test_calibration_errors_name_the_fix():
    with pytest.raises(ValueError, match="needs at least 17 successful held-out episodes with scored decisions, "
                                         "got 10; record 7 more"):
        rules.calibrate_rule(synthetic_episodes(10, 0, 20, seed=0), rules.RuleParams("band"), ALPHA)
    one_decision = synthetic_episodes(20, 0, 1, seed=0)
    with pytest.raises(ValueError, match="fewer than 2 scored decisions"):
        rules.calibrate_rule(one_decision, rules.RuleParams("running"), ALPHA)
    with pytest.raises(ValueError, match="unknown alert rule"):
        rules.RuleParams("early")


def test_calibrated_rule_round_trips_through_json():
    rule = rules.calibrate_rule(synthetic_episodes(30, 0, 30, seed=5), rules.RuleParams("band", 3, 1, 0.5), ALPHA)
    again = rules.CalibratedRule.from_dict(rule.to_dict())
    ep = synthetic_episodes(0, 1, 30, seed=6)[0]
    assert again.params == rule.params and again.threshold == rule.threshold
    assert np.array_equal(again.running(ep), rule.running(ep)) and again.judge(ep) == rule.judge(ep)
    assert rules.clear_level(rule.params, 1.0) == pytest.approx(1.0 + math.log(0.5))
    assert rules.clear_level(rules.RuleParams("running", clear_ratio=0.5), 2.0) == 1.0


def test_cross_fit_judges_every_episode_once_with_binomial_intervals():
    eps = synthetic_episodes(60, 30, 30, seed=8)
    out = rules.cross_fit(eps, rules.RuleParams("running"), ALPHA, k=5, seed=0)
    assert out["successes"] == 60 and out["failures"] == 30 and out["skipped_episodes"] == 0
    ci = binomtest(out["false_alerts"], 60).proportion_ci(method="exact")
    assert out["false_alert_ci"] == pytest.approx([ci.low, ci.high])
    assert out["true_alert_rate"] == out["true_alerts"] / 30
    # too few successes in the training folds: counted as skipped, never silently judged
    few = rules.cross_fit(synthetic_episodes(8, 4, 10, seed=9), rules.RuleParams("running"), ALPHA, k=2)
    assert few["successes"] == few["failures"] == 0 and few["skipped_episodes"] == 12
