"""Detectors over named signals: the false-alert guarantee of FIPER's rule and of the
Bonferroni (min-p) fusion on fresh episodes from a known distribution, their semantics against the single-signal
rules, labelled (Youden) calibration, and the offline study's API."""
import numpy as np
import pytest
from scipy.stats import binom, binomtest

from monitor_service import signals as D
from monitor_service import rules

PAIRS = 300


def episode(rng, success, n, shift_a=0.0, shift_b=0.0, rho=0.5):
    """Two signals per decision, correlated (rho) log-normal noise independent of the index; a failure's
    signals drift up over its second half by shift_a / shift_b (log units). ``stac`` has no first value."""
    z = rng.normal(size=(2, n))
    z[1] = rho * z[0] + np.sqrt(1 - rho ** 2) * z[1]
    ramp = np.clip((np.arange(n) - n / 2) / (n / 2), 0, 1) if not success else np.zeros(n)
    a = np.exp(-2.0 + 0.5 * z[0] + shift_a * ramp)
    b = np.exp(0.0 + 0.4 * z[1] + shift_b * ramp)
    b[0] = np.nan
    return D.SignalEpisode({"nmse": a, "stac": b}, success, episode=f"e{rng.integers(1 << 30)}")


@pytest.mark.parametrize("alpha", [0.1, 0.2])
@pytest.mark.parametrize("combination", ["fiper", "bonferroni", "single"])
def test_each_combination_keeps_its_false_alert_promise_on_fresh_successes(combination, alpha):
    """Independent (calibration set, fresh success) pairs, lengths 5-60: the alerted count is Binomial(PAIRS, p)
    with p <= alpha; a one-sided binomial test against alpha does not reject at 0.001."""
    signals = ("stac",) if combination == "single" else ("nmse", "stac")
    spec = D.DetectorSpec(signals, combination, "successes", rules.RuleParams("running"))
    alerts = 0
    for i in range(PAIRS):
        rng = np.random.default_rng([38, int(alpha * 100), i])
        cal = [episode(rng, True, int(rng.integers(5, 61))) for _ in range(60)]
        detector = D.calibrate_detector(spec, cal, alpha, seed=i)
        alerts += detector.judge(episode(rng, True, int(rng.integers(5, 61))))["alerted"]
    assert binomtest(alerts, PAIRS, alpha, alternative="greater").pvalue > 1e-3, alerts
    if combination != "fiper":   # an AND of two signals is conservative by design; the others fire
        assert alerts >= binom.ppf(0.001, PAIRS, alpha / 4), alerts


def test_fiper_needs_both_signals_and_bonferroni_either():
    rng = np.random.default_rng(1)
    cal = [episode(rng, True, 40) for _ in range(80)]
    params = rules.RuleParams("running")
    one = [episode(rng, False, 40, shift_a=4.0) for _ in range(40)]            # only nmse drifts
    both = [episode(rng, False, 40, shift_a=4.0, shift_b=4.0) for _ in range(40)]
    fiper = D.calibrate_detector(D.DetectorSpec(("nmse", "stac"), "fiper", params=params), cal, 0.1)
    bonf = D.calibrate_detector(D.DetectorSpec(("nmse", "stac"), "bonferroni", params=params), cal, 0.1)
    rate = lambda det, eps: np.mean([det.judge(e)["alerted"] for e in eps])   # noqa: E731
    assert rate(bonf, one) > 0.9 and rate(fiper, one) < 0.2
    assert rate(fiper, both) > 0.9 and rate(bonf, both) > 0.9
    # bonferroni calibrates each signal at alpha / 2: its thresholds are those of single rules at 0.05
    single = D.calibrate_detector(D.DetectorSpec(("stac",), params=params), cal, 0.05)
    assert bonf.rules["stac"].threshold == pytest.approx(single.rules["stac"].threshold)


def test_fiper_alerts_at_the_first_step_where_both_rules_are_over():
    rng = np.random.default_rng(2)
    cal = [episode(rng, True, 30) for _ in range(60)]
    params = rules.RuleParams("running")
    fiper = D.calibrate_detector(D.DetectorSpec(("nmse", "stac"), "fiper", params=params), cal, 0.2)
    for _ in range(30):
        e = episode(rng, False, 30, shift_a=3.0, shift_b=3.0)
        flags = {s: D.SignalFlags.of(fiper.rules[s], e.series(s)) for s in ("nmse", "stac")}
        over = [set(f.steps[f.over].tolist()) for f in flags.values()]
        both = sorted(over[0] & over[1])
        judged = fiper.judge(e)
        assert judged["step"] == (both[0] if both else None)
        # each rule's "over" is the pure rule's condition: debounce values above their thresholds
        f = flags["nmse"]
        first = rules.first_alert(f.values, f.thresholds, params.debounce)
        assert (None if not f.over.any() else int(np.flatnonzero(f.over)[0])) == first


def test_labelled_calibration_maximises_youden_and_promises_nothing():
    rng = np.random.default_rng(3)
    cal = [episode(rng, True, 30) for _ in range(60)] + [episode(rng, False, 30, shift_a=1.0) for _ in range(30)]
    spec = D.DetectorSpec(("nmse",), calibration="labelled", params=rules.RuleParams("running"))
    det = D.calibrate_detector(spec, cal, 0.1)
    rule = det.rules["nmse"]
    stat = lambda e: rules.alert_statistic(np.log(rule.running(e.series("nmse"))), 2)   # noqa: E731
    s = np.array([stat(e) for e in cal if e.success])
    f = np.array([stat(e) for e in cal if not e.success])
    j = lambda c: np.mean(f > c) - np.mean(s > c)   # noqa: E731
    assert j(rule.level) == pytest.approx(max(j(c) for c in np.concatenate([s, f])))
    assert "no false-alert guarantee" in det.note and np.isnan(rule.alpha)
    with pytest.raises(ValueError, match="needs failed held-out episodes"):
        D.calibrate_detector(spec, [e for e in cal if e.success], 0.1)


def test_study_api_returns_an_alert_step_or_none_per_test_episode():
    rng = np.random.default_rng(4)
    cal = [episode(rng, True, 30) for _ in range(60)] + [episode(rng, False, 30, 3.0, 3.0) for _ in range(20)]
    test = [episode(rng, True, 30) for _ in range(10)] + [episode(rng, False, 30, 3.0, 3.0) for _ in range(10)]
    out = D.study_alerts(cal, test, alpha=0.1)
    assert set(out) == {"nmse band", "nmse band [labelled]", "stac band", "stac band [labelled]",
                        "fiper(nmse+stac) band", "bonferroni(nmse+stac) band"}
    for name, steps in out.items():
        assert len(steps) == 20 and all(s is None or (isinstance(s, int) and 0 <= s < 30) for s in steps)
        assert sum(s is not None for s in steps[10:]) >= 8, name   # the drifting failures alert
    judged, refused = D.study_judgements(cal[:10], test, alpha=0.1)
    assert not judged and "needs at least 17 successful held-out episodes" in refused["nmse band"]
    # a calibrated detector round-trips through JSON (the service stores it)
    det = D.calibrate_detector(D.DetectorSpec(("nmse", "stac"), "bonferroni"), cal, 0.1)
    again = D.CalibratedDetector.from_dict(det.to_dict())
    assert [again.judge(e) for e in test] == [det.judge(e) for e in test]


def test_bad_detector_specs_name_the_fix():
    with pytest.raises(ValueError, match="a fiper detector takes 2 distinct signals"):
        D.DetectorSpec(("a",), "fiper")
    with pytest.raises(ValueError, match="unknown combination"):
        D.DetectorSpec(("a", "b"), "vote")
    with pytest.raises(ValueError, match="one value per decision"):
        D.SignalEpisode({"a": np.ones(3), "b": np.ones(4)})
