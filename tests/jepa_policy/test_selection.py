"""Leakage-free checkpoint selection: the paired bootstrap against a reference, and the rule on a real run."""
import json

import numpy as np
import pytest

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_policy.selection import eval_snapshots, paired_bootstrap, select_checkpoint, wilson_ci
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


def test_selection_confirms_on_fresh_seeds(pusht_demo_file, tmp_path):
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path / "run"), steps=6, warmup_steps=0, batch_size=4,
                      eval_every=2, eval_episodes=2, eval_max_steps=30, model={"width": 32, "layers": 1, "heads": 2})
    train(cfg, demos)
    run = tmp_path / "run"
    assert sorted(eval_snapshots(run)) == [2, 4, 6]
    out = select_checkpoint(run, ladder=(2, 4), num_envs=2, max_steps=30)
    curve = json.loads((run / "eval_curve.json").read_text())
    top = sorted(curve, key=lambda p: (-p["success_rate"], -p["step"]))[:2]
    assert [c["step"] for c in out["candidates"]] == [p["step"] for p in top]   # chosen on the selection seeds
    assert out["pick"]["step"] in {p["step"] for p in top}
    assert out["pick"]["fresh_episodes"] in (2, 4) and out["fresh_seed"] == 1_000_000
    assert out["decided"] == (out["difference_first_minus_second"]["ci95"][0] > 0 or
                              out["difference_first_minus_second"]["ci95"][1] < 0)
    assert set(out["protocols"]) >= {"best", "mean_last5", "mean_all", "last"}
    (run / "checkpoints" / "eval_step2.pt").unlink()
    (run / "checkpoints" / "eval_step4.pt").unlink()
    with pytest.raises(ValueError, match="selection needs two"):
        select_checkpoint(run, ladder=(2,))
