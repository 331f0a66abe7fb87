"""The main job's --quick path end to end: real demos, real training steps, real server, real client, real report.

The report's numbers are checked against the stored records and the monitor's own database.
"""
from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from jepa_policy.demo import cli as demo_cli
from jepa_policy.demo import job as demo
from jepa_policy.demo.report import EARLY_DECISIONS, early_score, paired_comparison, wilson_ci
from jepa_policy.checkpoint import load_checkpoint


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "quick"
    summary = demo.run(demo.MODES["quick"], out)
    return out, summary


def _records(out):
    return [json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()]


def test_report_files_exist(quick_run):
    out, summary = quick_run
    for name in ("report.md", "summary.json", "records.jsonl", "learning_curves.png", "roc.png",
                 "nmse_distributions.png", "frames.png", "monitor.db"):
        assert (out / name).stat().st_size > 0, name
    page = (out / "report.md").read_text()
    for figure in ("learning_curves.png", "roc.png", "nmse_distributions.png", "frames.png"):
        assert f"]({figure})" in page
    assert set(summary["timing"]["steps_s"]) == {
        "1/8 scripted demonstrations", "2/8 training JEPA Policy and MIP (same seed, data and budget)",
        "3/8 imitation ceiling of these demonstrations (true-state policy, same episodes)",
        "4/8 monitor service + monitored rollouts", "5/8 decision latency (JEPA vs MIP, interleaved)",
        "6/8 failure prediction compared (every signal on the same labelled episodes, faults)",
        "7/8 audits (collapse, retrieval, gradients) and checkpoint selection", "8/8 report"}


def test_failure_prediction_step_compares_every_signal_on_its_own_episodes(quick_run):
    out, summary = quick_run
    cfg, f = demo.MODES["quick"], summary["failure"]
    rows = [json.loads(line) for line in (out / "failure_records.jsonl").read_text().splitlines()]
    per_arm = cfg.failure_episodes + cfg.failure_fault_episodes * len(cfg.failure_faults)
    assert f["episodes"] == len(rows) == 2 * per_arm
    monitored = {r["seed"] for r in _records(out)}
    assert not monitored & {r["seed"] for r in rows}          # a seed block of its own
    for arm in ("jepa", "mip"):
        nat = [r for r in rows if r["arm"] == arm and r["regime"] == "natural"]
        faulted = [r for r in rows if r["arm"] == arm and r["regime"] == "block_displaced"]
        assert len(nat) == cfg.failure_episodes and len(faulted) == cfg.failure_fault_episodes
        assert all(r["fault_onset"] == 30 for r in faulted)
        assert {r["seed"] for r in faulted} <= {r["seed"] for r in nat}   # each has its natural twin
        d = nat[0]["decisions"][1]
        assert {"stac", "rnd", "pca_kmeans", "mahalanobis"} <= set(d["scores"])
        assert (d.get("nmse") is not None) == (arm == "jepa")
    groups = json.loads((out / "failure_compare.json").read_text())["groups"]
    assert {g["arm"] for g in groups.values()} == {"jepa", "mip"}
    jepa = next(g for g in groups.values() if g["arm"] == "jepa")
    assert {"nmse", "nmse_persistence", "stac", "rnd", "pca_kmeans", "mahalanobis", "random"} <= set(jepa["signals"])
    assert set(jepa["views"]) == {"prefix", "whole"} and jepa["views"]["prefix"]["decisions"] == 10
    page = (out / "report.md").read_text()
    assert "## Failure prediction compared" in page and "### Ranking, prefix" in page
    assert "| stac |" in page and "](failure_roc.png)" in page and (out / "failure_roc.png").stat().st_size > 0


def test_ceiling_is_measured_on_the_same_episodes_and_compared(quick_run):
    out, summary = quick_run
    cfg, c = demo.MODES["quick"], summary["ceiling"]
    assert c["episodes"] == cfg.calib_episodes + cfg.live_episodes and c["steps"] == cfg.ceiling_steps
    assert c["rate"] == pytest.approx(c["successes"] / c["episodes"])
    assert c["ci95"] == pytest.approx(list(wilson_ci(c["successes"], c["episodes"])))
    page = (out / "report.md").read_text()
    assert "| ceiling: true-state policy |" in page and "imitation ceiling of these demonstrations" in page
    assert "aim" not in page.lower()


def test_audits_and_selection_of_every_run(quick_run):
    out, summary = quick_run
    audits = summary["audits"]
    assert set(audits) == {"jepa seed 42", "mip seed 42"}
    for run, a in audits.items():
        views = a["collapse"]["views"]
        assert a["collapse"]["primary"] == "c_t" and views["c_t"]["dim"] == 32   # the quick preset's width
        assert views["e_rgb"]["dim"] == 64 and 0.0 <= views["c_t"]["te32"] <= 1.0
        sel = a["selection"]
        assert [c["step"] for c in sel["candidates"]] and sel["pick"]["fresh_episodes"] in (2, 4)
        assert sel["pick"]["step"] in (15, 30)
    assert "retrieval" in audits["jepa seed 42"] and "retrieval" not in audits["mip seed 42"]
    assert audits["mip seed 42"]["gradients"]["gradient_share"] == 0.0
    r = audits["jepa seed 42"]["retrieval"]["all"]
    assert r["pool"] == 32 and r["queries"] == 64 and 0 < r["permutation_p"] <= 1
    assert "## Audits of every checkpoint" in (out / "report.md").read_text()


def test_demonstrations_end_past_the_threshold_and_are_reported(quick_run):
    out, summary = quick_run
    d = summary["demonstrations"]
    finish = demo.MODES["quick"].finish_threshold
    assert d["episodes"] == demo.MODES["quick"].demos and d["finish_threshold"] == finish
    assert d["task_threshold"] == 0.8 < finish
    assert d["final_coverage"][0] >= finish   # every kept demo ended at the finish coverage, not at 0.8
    page = (out / "report.md").read_text()
    assert "## Demonstrations" in page
    assert f"reaches {finish:g} (final coverage min {d['final_coverage'][0]:.3f}" in page
    assert "), past the task's success threshold 0.8" in page
    # the rollouts are judged at the task's threshold (0.8), not at the demos' finish coverage
    ckpt = load_checkpoint(out / "runs" / "jepa_seed42" / "checkpoints" / "latest.pt")
    assert ckpt["env_args"]["env_kwargs"]["success_threshold"] == 0.8
    assert ckpt["env_args"]["expert"]["finish_threshold"] == finish
    for rec in _records(out):
        assert rec["success"] == (rec["max_reward"] >= 0.8)


def test_best_of_k_starts_are_reported_as_trained(quick_run):
    out, summary = quick_run
    page = (out / "report.md").read_text()
    assert "## Training starts (best-of-K" in page
    for arm in ("jepa", "mip"):
        run_dir = out / "runs" / f"{arm}_seed42"
        sel = json.loads((run_dir / "init_selection.json").read_text())
        assert summary["init_selection"][f"{arm} seed 42"] == sel
        assert sel["seeds"] == [42, 10_042] and sel["chosen_seed"] == sel["seeds"][int(np.argmin(sel["scores"]))]
        assert f"| {arm} seed 42 | 42, 10042 |" in page
        ckpt = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
        assert ckpt["step"] == 30 and ckpt["init_selection"] == sel
        rows = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
        assert rows[0]["step"] == 5 and rows[-1]["step"] == 30   # one curve from the start (log_every 5)


def test_success_rates_match_records(quick_run):
    out, summary = quick_run
    records = _records(out)
    cfg = demo.MODES["quick"]
    for arm in ("jepa", "mip"):
        rs = [r for r in records if r["arm"] == arm]
        assert len(rs) == cfg.calib_episodes + cfg.live_episodes
        k = sum(r["success"] for r in rs)
        s = summary["success"][arm]
        assert s["successes"] == k and s["episodes"] == len(rs)
        assert s["rate"] == pytest.approx(k / len(rs))
        assert s["ci95"] == pytest.approx(list(wilson_ci(k, len(rs))))
        assert f"| {arm} | {100 * k / len(rs):.1f}% |" in (out / "report.md").read_text()
    # seeded rollouts: every arm ran the same rollout seeds
    seeds = {arm: sorted(r["seed"] for r in records if r["arm"] == arm) for arm in ("jepa", "mip")}
    assert seeds["jepa"] == seeds["mip"]


def test_monitor_store_agrees_with_records(quick_run):
    out, summary = quick_run
    records = [r for r in _records(out) if r["arm"] == "jepa"]
    with sqlite3.connect(out / "monitor.db") as db:
        tables = {row[0] for row in db.execute("select name from sqlite_master where type='table'")}
        assert "episodes" in tables, tables
        rows = db.execute("select id, success, held_out, early_score from episodes").fetchall()
        n_alerts = db.execute("select count(*) from alerts").fetchone()[0]
    stored = {r[0]: r for r in rows}
    assert set(stored) == {r["episode_id"] for r in records}
    for rec in records:
        _, success, held_out, score = stored[rec["episode_id"]]
        assert bool(success) == rec["success"]
        assert bool(held_out) == (rec["phase"] == "calibration")
        mine = early_score(rec["decisions"])
        if mine is None:
            assert score is None
        else:  # the service recomputed NMSE from the streamed float32 latents
            assert score == pytest.approx(mine, rel=1e-5)
    assert summary["live"]["alerts"] == n_alerts


def test_calibration_matches_sklearn_or_says_why_there_is_none(quick_run):
    """The quick run's 30 training steps may leave every held-out rollout failed (as on the machine this was
    written on): then the calibration must be the service's refusal of one outcome class, not any error.
    test_the_main_jobs_calibration_is_sklearns_auroc below compares with sklearn whatever the quick run did."""
    out, summary = quick_run
    held = [r for r in _records(out) if r["arm"] == "jepa" and r["phase"] == "calibration"]
    scored = [(early_score(r["decisions"]), not r["success"]) for r in held]
    scored = [(s, y) for s, y in scored if s is not None]
    cal = summary["calibrations"]["42"] if "42" in summary["calibrations"] else summary["calibrations"][42]
    labels = np.array([y for _, y in scored], dtype=int)
    if len(scored) < EARLY_DECISIONS or labels.min() == labels.max():
        outcomes = "failures" if labels.min() == 1 else "successes"
        assert cal == {"error": f"need both successes and failures, got {len(held)} {outcomes} of {len(held)} "
                                "episodes; record more held-out episodes with outcomes"}
        return
    scores = np.array([s for s, _ in scored])
    assert cal["result"]["auroc"] == pytest.approx(roc_auc_score(labels, scores))
    assert cal["result"]["n_failure"] == labels.sum()
    from jepa_policy.demo.report import MIN_CLASS_FOR_AUROC
    small = min(cal["result"]["n_success"], cal["result"]["n_failure"]) < MIN_CLASS_FOR_AUROC
    assert ("**Caveat:**" in (out / "report.md").read_text()) == small


def test_the_main_jobs_calibration_is_sklearns_auroc(tmp_path):
    """The main job's monitor (a real server) calibrates from episodes streamed as the job streams them, with both
    outcomes for certain: its AUROC is sklearn's over report.early_score of the same decisions."""
    from monitor_service.scoring import nmse_rows

    rng = np.random.default_rng(7)
    monitor = demo.Monitor(tmp_path, fresh=True)
    try:
        monitor.register_task(8)
        client = monitor.client()
        labels, scores = [], []
        for i in range(40):
            success, episode = i % 2 == 0, f"ep-{i}"
            z = rng.normal(size=(10, 8)).astype(np.float32)
            z_hat = (z + rng.normal(scale=0.5 if success else 0.6, size=z.shape)).astype(np.float32)
            nmse = nmse_rows(z_hat, z)
            for j in range(10):
                client.decision(demo.TASK, episode, 8 * j, 4, z_hat[j], checkpoint="ck", held_out=True, group="g")
                client.target(episode, 8 * j + 4, z[j])
            client.outcome(episode, success, held_out=True, group="g", length=80)
            labels.append(int(not success))
            scores.append(early_score([{"step": 8 * j, "nmse": float(v)} for j, v in enumerate(nmse)]))
        assert client.close(timeout=60)
        cal = monitor.calibrate("ck", demo.MODES["quick"])
    finally:
        monitor.close()
    assert "error" not in cal, cal
    assert cal["result"]["n_failure"] == 20 and cal["result"]["n_success"] == 20
    assert cal["result"]["auroc"] == pytest.approx(roc_auc_score(labels, scores), rel=1e-6)
    assert 0.5 < cal["result"]["auroc"] < 1.0        # a signal, not a separation: the comparison is not trivial


def test_paired_comparison_reference():
    diffs = np.array([4.0, 6.5, 3.0, 8.0])
    p = paired_comparison(diffs, n_boot=2000)
    from scipy import stats
    t = stats.ttest_1samp(diffs, 0.0).confidence_interval(0.95)
    assert p["t_interval"] == pytest.approx([t.low, t.high])
    assert p["sign_test_p"] == pytest.approx(0.125)  # 4 of 4 positive: exact two-sided 2 * 0.5**4
    assert p["bootstrap_interval"][0] <= diffs.mean() <= p["bootstrap_interval"][1]


def test_auroc_caveat_flags_small_classes():
    from jepa_policy.demo.report import MIN_CLASS_FOR_AUROC, auroc_caveat

    assert auroc_caveat(MIN_CLASS_FOR_AUROC, 50) is None
    assert auroc_caveat(40, MIN_CLASS_FOR_AUROC) is None
    one = auroc_caveat(1, 38)
    assert one is not None and "only 1 held-out success episode:" in one
    few = auroc_caveat(30, 3)
    assert few is not None and "only 3 held-out failure episodes" in few


def test_report_summary_names_threshold_and_false_alarms():
    from jepa_policy.demo.report import render_markdown

    rate = {"rate": 0.3, "ci95": [0.2, 0.4], "episodes": 10, "per_seed": {42: 0.3}, "mean_best_reward": 0.6,
            "mean_length": 100.0}
    result = {"n_failure": 20, "n_success": 12, "auroc": 0.7, "auroc_ci_low": 0.5, "auroc_ci_high": 0.85,
              "n_bootstrap": 100, "average_precision": 0.8, "permutation_p": 0.04, "n_permutation": 100,
              "youden_threshold": 0.1234567, "youden_bacc_in_sample": 0.7, "youden_bacc_held_out": 0.6,
              "held_out_method": "2-fold", "alpha": 0.1,
              "rule": {"params": {"kind": "band", "window": 5, "debounce": 2, "clear_ratio": 0.8},
                       "threshold": 0.17552496612009205, "note": "threshold = 10-th smallest of 10"}}
    live = {"episodes": 24, "failures": 14, "alerts": 8, "alerted_episodes": 8, "alerted_failures": 7,
            "alerted_successes": 1}
    summary = {"success": {"jepa": rate, "mip": rate}, "latency": {"arms": {}},
               "calibrations": {42: {"result": result, "threshold": 0.17552496612009205, "checkpoint": "c",
                                     "rule": "band"}},
               "live": live}
    page, text = render_markdown(summary, {"mode": "default"}, {})
    assert page.startswith("# JEPA Policy on PushT: main job report (default mode)\n")
    assert "band rule threshold 0.1755" in text and "0.175524" not in page
    assert "Alert rule **band** (window 5, debounce 2): threshold 0.1755, so at most 0.1 of successful" in page
    assert "7/14 failures and 1/10 successes flagged" in text
    assert "8 intervention alerts on 8 episodes (7 failures, 1 success)." in page
    summary["ceiling"] = {"rate": 0.6, "ci95": [0.5, 0.7], "episodes": 10, "successes": 6, "train_seed": 42,
                          "mean_best_reward": 0.8, "steps": 4000}
    page, text = render_markdown(summary, {"mode": "default"}, {})
    assert "| ceiling: true-state policy | 60.0% | [50.0%, 70.0%] | 10 |" in page
    assert "jepa (30.0%) is below it: its interval ends before the ceiling's begins" in page
    assert "ceiling     : 60.0% (95% CI 50.0%-70.0%, n=10" in text
    rate["ci95"] = [0.2, 0.65]
    assert "jepa (30.0%) cannot be told apart from it" in render_markdown(summary, {"mode": "default"}, {})[0]
    rate["ci95"] = [0.2, 0.4]
    live.update(alerts=1, alerted_episodes=1, alerted_failures=1, alerted_successes=0)
    page, text = render_markdown(summary, {"mode": "default"}, {})
    assert "1 intervention alert on 1 episode (1 failure, 0 successes)." in page
    assert "live: 1 alert on 1 of 24 episodes" in text
    page, text = render_markdown(summary, {"mode": "default", "train_overrides": {"steps": 6000}}, {})
    assert page.startswith("# JEPA Policy on PushT: main job report (default mode, 6000 training steps per arm)")


def test_report_describes_demonstrations_from_an_older_file(pusht_demo_file, tmp_path):
    """A file written before the expert's finish coverage was recorded is described as ending at success."""
    import h5py

    from jepa_policy.demo.report import dataset_summary, render_markdown

    old = tmp_path / "old.hdf5"
    old.write_bytes(pusht_demo_file.read_bytes())
    with h5py.File(old, "r+") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        del env_args["expert"]["finish_threshold"]
        f["data"].attrs["env_args"] = json.dumps(env_args)
        lengths = [int(f["data"][k].attrs["num_samples"]) for k in f["data"] if k.startswith("demo_")]
    d = dataset_summary(old)
    assert d["finish_threshold"] is None and d["task_threshold"] == 0.8 and d["episodes"] == 4
    assert d["transitions"] == sum(lengths) and d["mean_length"] == pytest.approx(np.mean(lengths))
    assert 0.8 <= d["final_coverage"][0] <= d["final_coverage"][1]
    rate = {"rate": 0.7, "ci95": [0.6, 0.8], "episodes": 10, "per_seed": {42: 0.7}, "mean_best_reward": 0.8,
            "mean_length": 60.0}
    summary = {"success": {"jepa": rate}, "latency": {"arms": {}}, "calibrations": {}, "demonstrations": d,
               "live": {"episodes": 0, "failures": 0, "alerts": 0, "alerted_episodes": 0, "alerted_failures": 0,
                        "alerted_successes": 0}}
    page, text = render_markdown(summary, {"mode": "default"}, {})
    assert f"4 scripted demonstrations, {sum(lengths)} transitions" in page
    assert "each ends when the task succeeds (final coverage min" in page and "past the task's" not in page


def test_steps_override_changes_only_the_training_steps(capsys):
    cfg, name = demo.demo_config("default", 6000)
    base = demo.MODES["default"]
    assert name == "default-steps6000" and cfg.train_overrides == {"steps": 6000} and cfg.mode == "default"
    assert (cfg.seeds, cfg.calib_episodes, cfg.live_episodes, cfg.preset) == (base.seeds, base.calib_episodes,
                                                                              base.live_episodes, base.preset)
    quick, _ = demo.demo_config("quick", 7)
    assert quick.train_overrides["steps"] == 7 and quick.train_overrides["eval_every"] == 15
    assert demo.demo_config("full") == (demo.MODES["full"], "full")
    with pytest.raises(SystemExit):
        demo_cli.main(["--steps", "0"])
    assert "--steps must be a positive number of training steps, got 0" in capsys.readouterr().err
