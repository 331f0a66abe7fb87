"""Leakage-free checkpoint selection: the paired bootstrap against a reference, and the rule on a real run."""
import json

import numpy as np
import pytest

from jepa_envs.datasets.hdf5 import load_dataset
from scipy.stats import binomtest

from jepa_policy.selection import confirm_and_report, eval_snapshots, paired_bootstrap, select_checkpoint, wilson_ci
from jepa_policy.train import load_config, train


def test_paired_bootstrap_against_a_direct_resampling():
    rng = np.random.default_rng(0)
    a, b = rng.random(50) < 0.7, rng.random(50) < 0.4
    out = paired_bootstrap(a, b, n_resamples=4000, seed=3)
    diff = a.astype(float) - b.astype(float)
    idx = np.random.default_rng(3).integers(0, 50, size=(4000, 50))
    lo, hi = np.percentile(diff[idx].mean(axis=1), [2.5, 97.5])
    assert out["mean"] == pytest.approx(diff.mean()) and out["ci95"] == pytest.approx([lo, hi])
    assert out["episodes"] == 50
    with pytest.raises(ValueError, match="equally long"):
        paired_bootstrap(a, b[:10])


def test_wilson_interval_contains_the_rate():
    lo, hi = wilson_ci(7, 10)
    assert lo < 0.7 < hi and 0 <= lo and hi <= 1


def bernoulli_player(true_rate: dict, repetition: int):
    """Simulated rollouts: episode seed s of candidate c succeeds with probability true_rate[c] (fresh draws)."""
    def play(c, first_seed, episodes):
        return [bool(np.random.default_rng([repetition, c, first_seed + i]).random() < true_rate[c])
                for i in range(episodes)]
    return play


def test_the_reported_success_is_unbiased_where_the_confirmation_is_not():
    """The pick's success measured on the episodes that chose it is biased upwards (two candidates of
    true success 0.50 reported 0.529 on average). On the untouched report block the successes are Binomial(n, 0.5)
    exactly, overall and within each group the report shows (decided or not)."""
    reps, ladder = 200, (16, 32, 64)
    report = {True: [0, 0], False: [0, 0]}      # decided -> [successes, episodes]
    confirmation = [0, 0]
    for rep in range(reps):
        out = confirm_and_report(bernoulli_player({1: 0.5, 2: 0.5}, rep), [1, 2], fresh_seed=1_000_000,
                                 ladder=ladder, report_seed=2_000_000, seed=rep)
        pick = out["pick"]
        assert pick["fresh_episodes"] == 64 and pick["report_seed"] == 2_000_000
        report[out["decided"]][0] += round(pick["fresh_success_rate"] * 64)
        report[out["decided"]][1] += 64
        confirmation[0] += round(out["confirmation_success_rate"][pick["step"]] * out["confirmation_episodes"])
        confirmation[1] += out["confirmation_episodes"]
    total = [sum(v[0] for v in report.values()), sum(v[1] for v in report.values())]
    assert binomtest(*total, 0.5).pvalue > 1e-3, total
    for decided, (k, n) in report.items():
        if n:
            assert binomtest(k, n, 0.5).pvalue > 1e-3, (decided, k, n)
    # what was reported before: the pick's rate on its own confirmation episodes, well above the truth
    assert confirmation[0] / confirmation[1] > 0.515 and binomtest(*confirmation, 0.5).pvalue < 1e-3, confirmation


def test_report_block_must_be_untouched():
    play = bernoulli_player({1: 0.5, 2: 0.5}, 0)
    with pytest.raises(ValueError, match="overlaps the confirmation block"):
        confirm_and_report(play, [1, 2], fresh_seed=1_000_000, ladder=(4, 8), report_seed=1_000_004)
    seen = []
    confirm_and_report(lambda c, s, n: seen.append((c, s, n)) or [True] * n, [1, 2], fresh_seed=10, ladder=(4, 8),
                       report_seed=100, report_episodes=5)
    played = {s + i for _, s, n in seen[:-1] for i in range(n)}
    assert seen[-1][1:] == (100, 5) and played.isdisjoint(range(100, 105))


def test_selection_confirms_on_fresh_seeds(pusht_demo_file, tmp_path, capsys):
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path / "run"), steps=6, warmup_steps=0, batch_size=4,
                      eval_every=2, eval_episodes=2, eval_max_steps=30, model={"width": 32, "layers": 1, "heads": 2})
    train(cfg, demos)
    run = tmp_path / "run"
    assert sorted(eval_snapshots(run)) == [2, 4, 6]
    capsys.readouterr()
    out = select_checkpoint(run, ladder=(2, 4), num_envs=2, max_steps=30, progress=True)
    played = 2 * out["confirmation_episodes"] + out["pick"]["fresh_episodes"]   # both candidates, then the report
    assert f"selection: {played}episode" in capsys.readouterr().err.replace("\r", "\n").splitlines()[-1]
    curve = json.loads((run / "eval_curve.json").read_text())
    top = sorted(curve, key=lambda p: (-p["success_rate"], -p["step"]))[:2]
    assert [c["step"] for c in out["candidates"]] == [p["step"] for p in top]   # chosen on the selection seeds
    assert out["pick"]["step"] in {p["step"] for p in top}
    assert out["confirmation_episodes"] in (2, 4) and out["fresh_seed"] == 1_000_000
    assert out["pick"]["fresh_episodes"] == 4 and out["report_seed"] == out["pick"]["report_seed"] == 2_000_000
    assert out["decided"] == (out["difference_first_minus_second"]["ci95"][0] > 0 or
                              out["difference_first_minus_second"]["ci95"][1] < 0)
    assert set(out["protocols"]) >= {"best", "mean_last5", "mean_all", "last"}
    with pytest.raises(ValueError, match="overlaps the training-time evaluation seeds"):
        select_checkpoint(run, ladder=(2,), report_seed=cfg.eval_seed)
    (run / "checkpoints" / "eval_step2.pt").unlink()
    (run / "checkpoints" / "eval_step4.pt").unlink()
    with pytest.raises(ValueError, match="selection needs two"):
        select_checkpoint(run, ladder=(2,))
