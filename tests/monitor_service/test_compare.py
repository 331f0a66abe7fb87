"""``jepa-monitor compare`` on synthetic episode records whose answers are known: a signal that separates the
outcomes ranks and detects them perfectly, the random row sits at chance, the prefix view reads only the first
decisions, a fault's detection delay counts from its onset and an alert before the onset detects nothing, and
cross-fitting never calibrates on the episodes it judges (nor on a faulted episode's natural twin)."""
import gzip
import json
import subprocess
import sys

import numpy as np
import pytest

from monitor_service.offline import compare as cmp
from monitor_service.signals import DetectorSpec
from monitor_service.cli import main as monitor_main

ONSET = 30


def record(seed, success, n, regime="natural", onset=None, stac=None, nmse=None, arm="jepa"):
    """One record as ``jepa-policy eval --faults ... --out`` writes it: decisions every 8 env steps, NMSE known at
    the target step t + 4, STAC missing at the first decision. ``stac``/``nmse``: f(i, step, rng) -> value
    (default: uniform noise)."""
    rng = np.random.default_rng([seed, len(regime)])
    decisions = []
    for i in range(n):
        step = 8 * i
        decisions.append({"step": step, "target_step": step + 4,
                          "nmse": nmse(i, step, rng) if nmse else float(rng.random()),
                          "nmse_persistence": float(rng.random()),
                          "scores": {"stac": None if i == 0 else (stac(i, step, rng) if stac else float(rng.random())),
                                     "rnd": float(rng.random())}})
    row = {"seed": seed, "success": success, "length": 8 * n if success else 300, "regime": regime, "arm": arm,
           "checkpoint": f"{arm}.pt", "decisions": decisions}
    if onset is not None:
        row.update(fault=regime, fault_onset=onset)
    return row


def natural(count=90, stac=None, nmse=None, fail_every=3):
    """``count`` natural episodes, every ``fail_every``-th a 38-decision failure, the rest 12-21-decision
    successes; ``stac``/``nmse``: f(failed, i, step, rng)."""
    rows = []
    for seed in range(count):
        failed = seed % fail_every == 0
        rows.append(record(seed, not failed, 38 if failed else 12 + seed % 10,
                           stac=None if stac is None else (lambda i, s, g, f=failed: stac(f, i, s, g)),
                           nmse=None if nmse is None else (lambda i, s, g, f=failed: nmse(f, i, s, g))))
    return rows


def run(rows, **kw):
    kw.setdefault("n_bootstrap", 300)
    kw.setdefault("rule_names", ("fast",))
    return cmp.compare([cmp.episode_of(r) for r in rows], **kw)


def single(view, rule, signal):
    return view["detection"][rule]["detectors"][DetectorSpec((signal,), params=cmp.RULES[rule]).name]


def test_a_separating_signal_ranks_and_detects_every_failure_and_the_random_row_sits_at_chance():
    rows = natural(stac=lambda failed, i, s, g: (2.0 if failed else 0.0) + g.random())
    result = run(rows, rule_names=("default", "fast"), signals=["stac", "random", "absent"])
    g = result["groups"]["jepa:jepa.pt"]
    assert g["episodes"]["natural"] == {"episodes": 90, "successes": 60, "failures": 30, "twin_failed_too": 0,
                                        "no_twin": 0, "ended_before_onset": 0, "onset": None}
    assert g["signals"] == ["stac", "random"]      # a signal the records lack is left out
    for view in ("prefix", "whole"):
        v = g["views"][view]
        stac = v["ranking"]["natural"]["stac"]
        assert stac["auroc"] == 1.0 and stac["ci"] == [1.0, 1.0] and (stac["failures"], stac["successes"]) == (30, 60)
        assert stac["roc"]["tpr"][-1] == 1.0
        rnd = v["ranking"]["natural"]["random"]
        assert rnd["ci"][0] < 0.5 < rnd["ci"][1] and abs(rnd["auroc"] - 0.5) < 0.2
        for rule in ("default", "fast"):
            d = single(v, rule, "stac")["natural"]
            assert d["tpr"] == 1.0 and d["true_alerts"] == 30
            # conformal on successes at alpha 0.1: the false alerts of 60 clean successes within the binomial bound
            assert d["false_alert_ci"][0] <= 0.1 and d["false_alerts"] <= 12
            assert d["balanced_accuracy"] == pytest.approx((1 + d["tnr"]) / 2)
            assert d["lead_steps"]["n"] == 30 and d["lead_steps"]["median"] > 0
    text = cmp.summary_text(result)
    assert "stac 1.000 [1.00, 1.00]" in text and "natural 90 (30 failed)" in text


def test_the_prefix_view_reads_only_the_first_decisions_of_the_episodes_that_reach_them():
    # identical in the first 10 decisions of every episode; failures rise after them
    rows = natural(stac=lambda failed, i, s, g: 0.5 if i < 10 else (3.0 if failed else 0.5))
    rows.append(record(500, True, 6))   # too short for the prefix view
    g = run(rows, prefix=10)["groups"]["jepa:jepa.pt"]
    prefix, whole = g["views"]["prefix"], g["views"]["whole"]
    assert (prefix["episodes"], prefix["decisions"]) == (90, 10)
    assert (whole["episodes"], whole["decisions"]) == (91, None)
    assert prefix["ranking"]["natural"]["stac"]["auroc"] == 0.5     # every prefix ties
    assert whole["ranking"]["natural"]["stac"]["auroc"] == 1.0
    # the length-controlled cut also holds for detection: no prefix alert can come after decision 10
    d = single(prefix, "fast", "stac")["natural"]
    assert d["true_alerts"] == 0 and single(whole, "fast", "stac")["natural"]["true_alerts"] == 30


def kept(n, start=0):
    """The first ``n`` seeds from ``start`` whose natural episode succeeds (``natural()`` fails every third): a
    faulted failure on them is the fault's, not one its twin shares."""
    return [s for s in range(start, start + 2 * n) if s % 3][:n]


def faulted(seeds, regime, stac, nmse=None, success=False):
    """Faulted twins of natural seeds: failures of 38 decisions, or successes as long as the natural ones."""
    return [record(s, success, 12 + s % 10 if success else 38, regime, ONSET, stac=stac, nmse=nmse) for s in seeds]


def test_fault_delay_counts_from_the_onset_and_an_alert_before_it_detects_nothing():
    rows = natural()
    # the fault lifts STAC and NMSE from its onset on: the first decision after step 30 is step 32
    rows += faulted(kept(20), "block_displaced", lambda i, s, g: 5 + g.random() if s > ONSET else g.random(),
                    nmse=lambda i, s, g: 5 + g.random() if s + 4 > ONSET else g.random())
    # a spike before the onset only, then quiet: the first alert comes before the onset
    rows += faulted(kept(20, 30), "early_spike", lambda i, s, g: 9.0 if s < ONSET else 0.01 * g.random())
    # a harmless shift: successes under the fault, read for their alert rate
    rows += faulted(range(40, 60), "background_tint", lambda i, s, g: g.random(), success=True)
    g = run(rows, signals=["stac", "nmse"])["groups"]["jepa:jepa.pt"]
    assert g["episodes"]["block_displaced"]["onset"]["median"] == ONSET
    whole = g["views"]["whole"]
    stac = single(whole, "fast", "stac")
    assert stac["block_displaced"]["tpr"] == 1.0
    assert stac["block_displaced"]["delay_steps"]["median"] == 2          # known at step 32
    assert stac["block_displaced"]["delay_decisions"]["median"] == 2 / 8
    nmse = single(whole, "fast", "nmse")["block_displaced"]
    # every one is caught at its target step 36, or was alerted on by the noise before the onset (no detection)
    assert nmse["true_alerts"] + nmse["pre_onset_alerts"] == 20 and nmse["true_alerts"] >= 17
    assert nmse["delay_steps"]["median"] == (32 + 4) - ONSET
    spike = stac["early_spike"]
    assert spike["true_alerts"] == 0 and spike["pre_onset_alerts"] == 20 and spike["delay_steps"] is None
    benign = stac["background_tint"]
    assert benign["failures"] == 0 and benign["regime_successes"] == 20
    assert benign["regime_success_alert_ci"][0] <= 0.1      # noise like the clean successes': alerts near alpha
    # the ranking regime of a fault: its failures against the natural successes
    assert whole["ranking"]["block_displaced"]["stac"]["auroc"] == 1.0


def test_cross_fitting_never_calibrates_on_the_fold_it_judges_nor_on_a_faulted_episodes_twin(monkeypatch):
    rows = natural(stac=lambda failed, i, s, g: g.random() + failed)
    rows += faulted(range(0, 60, 2), "block_displaced", lambda i, s, g: g.random() + (s > ONSET))
    calls = []
    real = cmp.study_judgements

    def spy(calibration, test, alpha, specs, seed=0):   # who calibrates and who is judged, then the real one
        calls.append(([e.episode for e in calibration], [e.episode for e in test]))
        return real(calibration, test, alpha, specs, seed)

    monkeypatch.setattr(cmp, "study_judgements", spy)   # the name compare calls
    run(rows, folds=5, views=("whole",))
    assert len(calls) == 5
    judged = [e for _, test in calls for e in test]
    assert sorted(judged) == sorted(f"{r['regime']}-{r['seed']}" for r in rows)   # each episode judged once
    for calibration, test in calls:
        assert all(e.startswith("natural-") for e in calibration)
        seeds_calibrated = {int(e.split("-")[1]) for e in calibration}
        seeds_tested = {int(e.split("-")[1]) for e in test}
        assert not seeds_calibrated & seeds_tested       # a faulted episode's natural twin sits in its own fold
        assert len(calibration) + sum(e.startswith("natural-") for e in test) == 90


def test_labelled_calibration_is_judged_beside_the_conformal_one_and_combinations_keep_their_names():
    rows = natural(stac=lambda failed, i, s, g: g.random() + 1.5 * failed,
                   nmse=lambda failed, i, s, g: g.random() + 1.5 * failed)
    d = run(rows, views=("whole",))["groups"]["jepa:jepa.pt"]["views"]["whole"]["detection"]["fast"]
    assert {"stac band", "stac band [labelled]", "nmse band", "fiper(nmse+stac) band", "fiper(rnd+stac) band",
            "bonferroni(nmse+stac) band", "random band"} <= set(d["detectors"])
    # at alpha / 3 the 48 successes of a calibration fold are too few: refused with the reason, not judged
    assert "bonferroni(nmse+rnd+stac) band" not in d["detectors"]
    assert "success" in d["refused"]["bonferroni(nmse+rnd+stac) band"]


def test_checkpoints_are_never_pooled():
    rows = natural(stac=lambda failed, i, s, g: g.random() + 2 * failed)
    rows += [dict(record(r["seed"], r["success"], len(r["decisions"]), arm="mip")) for r in natural()]
    result = run(rows, views=("whole",), signals=["stac"])
    assert set(result["groups"]) == {"jepa:jepa.pt", "mip:mip.pt"}
    assert result["groups"]["jepa:jepa.pt"]["views"]["whole"]["ranking"]["natural"]["stac"]["auroc"] == 1.0
    assert result["groups"]["mip:mip.pt"]["views"]["whole"]["ranking"]["natural"]["stac"]["auroc"] < 0.8


def test_the_command_writes_json_and_markdown_and_refuses_bad_input_in_one_line(tmp_path, capsys):
    rows = natural(stac=lambda failed, i, s, g: g.random() + 2 * failed)
    rows += faulted(kept(10), "block_displaced", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    path = tmp_path / "records.jsonl.gz"
    with gzip.open(path, "wt") as f:
        f.writelines(json.dumps(r) + "\n" for r in rows)
    out_json, out_md = tmp_path / "c.json", tmp_path / "c.md"
    assert monitor_main(["compare", str(path), "--where", "arm=jepa", "--rules", "fast", "--bootstrap", "200",
                         "--signals", "stac,nmse",
                         "--out", str(out_json), "--out", str(out_md)]) == 0
    printed, err = capsys.readouterr()
    assert "natural 90 (30 failed), block_displaced 10 (10 failed)" in printed
    assert "compare: 100%" in err and "2/2" in err       # one checkpoint's two views, on a bar
    result = json.loads(out_json.read_text())
    assert result["groups"]["jepa:jepa.pt"]["views"]["whole"]["ranking"]["natural"]["stac"]["auroc"] == 1.0
    md = out_md.read_text()
    assert "| stac | 1.000 [1.00, 1.00] | 1.000 [1.00, 1.00] |" in md and "## Detection, block_displaced" in md
    assert monitor_main(["compare", str(path), "--where", "arm=jepa", "--rules", "fast", "--bootstrap", "200",
                         "--signals", "stac,nmse", "--json", "--no-progress"]) == 0
    printed, err = capsys.readouterr()
    assert json.loads(printed)["groups"] == result["groups"]   # --json: the same figures, printed
    assert "compare:" not in err

    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps(rows[0]) + "\n{not json\n")
    for argv, message in ((["compare", str(path), "--where", "arm"], "--where 'arm' needs KEY=VALUE"),
                          (["compare", str(tmp_path / "none.jsonl")], "does not exist"),
                          (["compare", str(bad)], f"{bad}:2: not JSON"),
                          (["compare", str(path), "--where", "arm=diffusion"], "no episode records in "),
                          (["compare", str(path), "--folds", "1"], "--folds must be >= 2"),
                          (["compare", str(path), "--rules", "slow"], "unknown rule setting"),
                          (["compare", str(path), "--out", str(tmp_path / "c.txt")], "name a .json or .md file")):
        assert monitor_main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("jepa-monitor: error: ") and message in err and "\n" not in err


def test_the_monitor_package_imports_no_plotting_library(tmp_path):
    code = "import sys, monitor_service.offline.compare, monitor_service.cli; sys.exit('matplotlib' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_figures_are_drawn_from_the_json_alone(tmp_path):
    pytest.importorskip("matplotlib")
    from monitor_service.offline.figures import main as figures_main

    rows = natural(stac=lambda failed, i, s, g: g.random() + 2 * failed)
    rows += faulted(range(10), "block_displaced", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    (tmp_path / "c.json").write_text(json.dumps(run(rows, signals=["stac", "nmse", "random"])))
    assert figures_main([str(tmp_path / "c.json"), "--out", str(tmp_path / "fig")]) == 0
    for name in ("compare_roc.png", "compare_delay.png"):
        assert (tmp_path / "fig" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "x.json").write_text("{}")
    assert figures_main([str(tmp_path / "x.json"), "--out", str(tmp_path / "fig")]) == 2


def test_episode_scores_aggregate_as_documented():
    v = np.array([1.0, np.nan, 3.0, 8.0, 2.0])
    assert [cmp.episode_score(v, how) for how in cmp.AGGREGATES] == [3.5, 8.0, 2.5, pytest.approx(13 / 3)]
    assert cmp.episode_score(np.array([np.nan])) is None
    with pytest.raises(ValueError, match="unknown aggregate"):
        cmp.episode_score(v, "sum")


def test_a_fault_is_caught_promptly_only_when_its_alert_comes_within_two_decisions_of_the_onset():
    """Over whole episodes a late alert still counts as detection (a long faulted failure is caught at last by any
    rule that keeps alerting); the prompt figures count only alerts known within PROMPT_DECISIONS of the onset."""
    rows = natural()
    rows += faulted(kept(20), "prompt", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    late = ONSET + (cmp.PROMPT_DECISIONS + 2) * cmp.N_ACTION_STEPS
    rows += faulted(kept(20, 30), "late", lambda i, s, g: 5 + g.random() if s > late else g.random())
    result = run(rows, signals=["stac", "random"], views=("whole",))
    stac = single(result["groups"]["jepa:jepa.pt"]["views"]["whole"], "fast", "stac")
    tnr = stac["prompt"]["tnr"]
    assert stac["prompt"]["tpr"] == stac["late"]["tpr"] == 1.0
    assert stac["prompt"]["prompt_alerts"] == 20 and stac["prompt"]["prompt_balanced_accuracy"] == (1 + tnr) / 2
    assert stac["late"]["prompt_alerts"] == 0 and stac["late"]["prompt_balanced_accuracy"] == tnr / 2
    rows_by_regime = {r["regime"]: r for r in cmp.best_rows(result, "whole", "fast")}
    assert rows_by_regime["prompt"]["best_prompt_detection"]["prompt_alerts"] == 20
    assert rows_by_regime["natural"]["best_prompt_detector"] is None      # no onset, no promptness
    # the goal as written: balanced accuracy >= 0.90 and a median delay <= 2 decisions; the late catches are all
    # 4-5 decisions after the onset, so nothing meets it there although their balanced accuracy is the same
    assert stac["late"]["balanced_accuracy"] == stac["prompt"]["balanced_accuracy"] >= cmp.GOAL_BALANCED_ACCURACY
    assert cmp.meets_goal(stac["prompt"]) and not cmp.meets_goal(stac["late"])
    assert rows_by_regime["prompt"]["best_goal_detector"] == "stac band"
    assert rows_by_regime["late"]["best_goal_detector"] is None and rows_by_regime["late"]["best_detector"]
    text = cmp.summary_text(result)
    assert "late             balanced acc >= 0.90 with median delay <= 2 decisions: no detector" in text
    assert "prompt           balanced acc >= 0.90 with median delay <= 2 decisions: stac band (" in text
    assert "prompt           within 2 decisions of the onset" in text and "(caught 20/20=1.00" in text
    (row,) = [r for r in cmp.detection_table(result, "whole", "fast", "late") if r.startswith("| stac band |")]
    assert f"| 0/20=0.00 ({stac['late']['prompt_balanced_accuracy']:.3f}) |" in row


def test_the_best_rows_leave_the_controls_out_and_show_the_chance_row_beside():
    assert cmp.is_control("random band [labelled]") and cmp.is_control("fiper(nmse_persistence+stac) band")
    assert not cmp.is_control("bonferroni(nmse+stac) band") and not cmp.is_control("rnd band")
    rows = natural(stac=lambda failed, i, s, g: g.random() + 2 * failed,
                   nmse=lambda failed, i, s, g: g.random() + 0.3 * failed)
    result = run(rows, views=("whole",), signals=["stac", "nmse", "nmse_persistence", "random"])
    (row,) = cmp.best_rows(result, "whole", "fast")
    assert row["best_signal"] == "stac" and row["best_auroc"]["auroc"] == 1.0
    assert row["random_auroc"]["auroc"] == result["groups"]["jepa:jepa.pt"]["views"]["whole"]["ranking"][
        "natural"]["random"]["auroc"]
    assert not cmp.is_control(row["best_detector"])
    name = "random band" + (" [labelled]" if "[labelled]" in row["best_detector"] else "")
    assert row["chance_detection"] == single_or_labelled(result, name)
    assert "chance row (random, same calibration)" in cmp.summary_text(result)


def single_or_labelled(result, name):
    return result["groups"]["jepa:jepa.pt"]["views"]["whole"]["detection"]["fast"]["detectors"][name]["natural"]


def test_nmse_ratio_is_nmse_over_persistence_known_at_the_target_step():
    row = record(3, True, 4)
    row["decisions"][2]["nmse_persistence"] = 0.0          # no defined ratio there: missing, not infinite
    e = cmp.episode_of(row)
    want = [d["nmse"] / d["nmse_persistence"] if d["nmse_persistence"] else np.nan for d in row["decisions"]]
    np.testing.assert_array_equal(e.values["nmse_ratio"], np.array(want))
    np.testing.assert_array_equal(e.known_at["nmse_ratio"], [4, 12, 20, 28])
    assert "nmse_ratio" not in cmp.episode_of(record(3, True, 4, arm="mip") | {"decisions": [
        {"step": 0, "scores": {"stac": None}}]}).values


def test_the_stacked_ranking_fuses_two_half_informative_signals_and_never_fits_on_what_it_scores():
    """Two signals each carry half of the outcome (failures high in one of them, independently): each alone ranks
    at about 0.75, their cross-fitted logistic stack above both; a stack of pure noise stays near chance (no
    overfitting leaks through the folds); faulted episodes (never in a fit) do not move the natural scores."""
    rng = np.random.default_rng(5)
    rows = []
    for seed in range(240):
        failed = seed % 2 == 0
        a, b = (rng.random() < 0.5, rng.random() < 0.5) if failed else (False, False)
        row = record(seed, not failed, 12, stac=lambda i, s, g, hi=a: g.random() + (3.0 if hi else 0.0),
                     nmse=lambda i, s, g, hi=b: g.random() + (3.0 if hi else 0.0))
        rows.append(row)
    eps = [cmp.episode_of(r) for r in rows]
    cmp.assign_folds(eps, 5, 0)
    members = ["nmse", "stac"]
    stacked = cmp.stacked_scores(eps, members, 10)
    assert set(stacked) == set(range(len(eps)))
    ranks = cmp.ranking(eps, members + ["rnd"], "natural", 10, 200, 0, stacked=(members, stacked))
    assert 0.6 < ranks["nmse"]["auroc"] < 0.85 and 0.6 < ranks["stac"]["auroc"] < 0.85
    assert ranks["stack"]["auroc"] > max(ranks["nmse"]["auroc"], ranks["stac"]["auroc"]) + 0.08
    assert ranks["stack"]["members"] == members

    noise = cmp.stacked_scores(eps, ["rnd", "nmse_persistence", "random"], 10)   # nothing to learn
    y = np.array([0 if e.success else 1 for e in eps])
    from sklearn.metrics import roc_auc_score
    assert abs(roc_auc_score(y, [noise[i] for i in range(len(eps))]) - 0.5) < 0.12

    faulted = [cmp.episode_of(record(s, False, 12, regime="block_displaced", onset=ONSET,
                                     stac=lambda i, st, g: 50.0, nmse=lambda i, st, g: 0.001)) for s in range(40)]
    both = eps + faulted
    cmp.assign_folds(both, 5, 0)
    with_faults = cmp.stacked_scores(both, members, 10)
    assert all(with_faults[i] == pytest.approx(stacked[i]) for i in range(len(eps)))
    assert cmp.stack_members(["nmse", "random", "nmse_persistence", "stac"]) == ["nmse", "stac"]


def test_failure_kinds_rank_apart_and_ours_is_differenced_with_others_on_the_same_episodes():
    """Natural failures of two kinds: NMSE separates one kind only, STAC the other; each kind's ranking says so,
    and the paired difference of NMSE against STAC equals the two AUROCs' difference with its interval."""
    rows = []
    for seed in range(120):
        kind = (None, "dropped", "never_grasped")[seed % 3]
        rows.append(record(seed, kind is None, 30 if kind else 12 + seed % 10,
                           nmse=lambda i, s, g, k=kind: (2.0 if k == "dropped" else 0.0) + g.random(),
                           stac=lambda i, s, g, k=kind: (2.0 if k == "never_grasped" else 0.0) + g.random()))
        if kind:
            rows[-1]["failure_kind"] = kind
    result = run(rows, signals=["nmse", "stac"])
    v = result["groups"]["jepa:jepa.pt"]["views"]["prefix"]
    kinds = v["ranking_by_kind"]
    assert set(kinds) == {"dropped", "never_grasped"}
    assert kinds["dropped"]["nmse"]["auroc"] == 1.0 and abs(kinds["dropped"]["stac"]["auroc"] - 0.5) < 0.2
    assert kinds["never_grasped"]["stac"]["auroc"] == 1.0 and abs(kinds["never_grasped"]["nmse"]["auroc"] - 0.5) < 0.2
    assert kinds["dropped"]["nmse"]["failures"] == 40 and kinds["dropped"]["nmse"]["successes"] == 40
    d = v["paired"]["nmse"]["stac"]
    nat = v["ranking"]["natural"]
    assert d["difference"] == pytest.approx(nat["nmse"]["auroc"] - nat["stac"]["auroc"])
    assert d["ci"][0] <= d["difference"] <= d["ci"][1]
    md = cmp.markdown(result)
    assert "## Ranking per natural failure kind" in md and "| nmse | 1.000 [1.00, 1.00] |" in md
    assert "## Paired AUROC differences" in md and "| stac |" in md
    assert "dropped (40 failures): best nmse 1.000" in cmp.summary_text(result)
    assert run(natural(), signals=["nmse"])["groups"]["jepa:jepa.pt"]["views"]["prefix"]["ranking_by_kind"] == {}


def with_latents(row, shift_from=None):
    """The record with ``z_now`` / ``z_real`` as ``--keep-latents`` writes them: a latent that is a function of
    (seed, step) only, shifted from env step ``shift_from`` on (the fault's visible effect); STAC is computed from
    the latent seen at the decision, as a signal of what the policy saw is."""
    def z(step):
        base = np.random.default_rng([row["seed"], step]).standard_normal(8)
        return (base + (5.0 if shift_from is not None and step >= shift_from else 0.0)).astype(np.float32)
    for i, d in enumerate(row["decisions"]):
        d["z_now"], d["z_real"] = z(d["step"]).tolist(), z(d["target_step"]).tolist()
        if i:
            d["scores"]["stac"] = float(np.asarray(d["z_now"]).sum())
    return row


def test_a_faulted_failure_that_looks_like_its_succeeding_twin_until_the_window_ends_caps_every_detector():
    """Faulted failures whose latents equal their natural twin's through PROMPT_DECISIONS decisions after the onset
    cannot be caught in time without the same alert on the twin: with a succeeding twin they lower the ceiling;
    with a failing twin they are not the fault's failures at all. A signal of what was seen stays under the
    ceiling; records without latents get no ceiling."""
    window_end = ONSET + cmp.PROMPT_DECISIONS * cmp.N_ACTION_STEPS
    rows = [with_latents(r) for r in natural()]
    hidden_seeds = {1, 2, 4, 5, 7, 8, 10}        # twins succeed (seed % 3 != 0); visible only after the window
    late_but_twin_failed = {3, 6, 9}               # the same, but their twins failed: not the fault's failures
    for seed in range(1, 31):
        late = seed in hidden_seeds or seed in late_but_twin_failed
        rows.append(with_latents(record(seed, False, 38, "slip", ONSET),
                                 shift_from=window_end + 2 if late else ONSET + 2))
    result = run(rows, signals=["stac"], views=("whole",))
    g = result["groups"]["jepa:jepa.pt"]
    ceiling = g["episodes"]["slip"]["prompt_ceiling"]
    assert g["episodes"]["slip"]["twin_failed_too"] == 10          # seeds 3, 6, ..., 30
    assert ceiling == {"failures": 20, "hidden_failures": 7, "prompt_tpr_ceiling": 13 / 20,
                       "prompt_balanced_accuracy_ceiling": (13 / 20 + 1) / 2}
    stac = single(g["views"]["whole"], "fast", "stac")["slip"]
    assert stac["failures"] == 20 and stac["prompt_alerts"] <= 20 - 7 and stac["prompt_balanced_accuracy"] <= \
        ceiling["prompt_balanced_accuracy_ceiling"]
    assert "7 failure(s) look like their succeeding natural twin until then" in cmp.summary_text(result)
    bare = run([{**r, "decisions": [{k: v for k, v in d.items() if k not in ("z_now", "z_real")}
                                    for d in r["decisions"]]} for r in rows], signals=["stac"], views=("whole",))
    assert "prompt_ceiling" not in bare["groups"]["jepa:jepa.pt"]["episodes"]["slip"]


def test_a_faulted_failure_whose_natural_twin_failed_too_is_not_the_faults_to_detect():
    """Under Lift's gripper slip every failure was one its natural twin (the same seed without the fault) shared:
    never grasped, so the weakened gripper changed nothing. Such failures are the policy's own: they are counted
    beside, and neither ranked nor detected as the fault's. A signal that rises only where the fault changed the
    outcome then reads as a perfect detector of the fault."""
    rows = natural()
    # the fault's own failures (twin succeeded) light STAC up after the onset; the shared ones stay quiet
    rows += faulted(kept(12), "slip", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    shared = [s for s in range(36) if s % 3 == 0]                      # twins failed
    rows += faulted(shared, "slip", lambda i, s, g: g.random())
    rows += faulted(shared[:5], "never_mattered", lambda i, s, g: g.random())
    # failures the twin shares, but the fault changed how: they light up after the onset, and that is reported
    rows += faulted(shared[:6], "changed_how", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    # successes under a fault whose episode ended before the onset never met it: not read for its alert rate
    rows += [record(s, True, 3, "too_late", ONSET) for s in kept(4)] + \
        [record(s, True, 12, "too_late", ONSET) for s in kept(4, 20)]
    result = run(rows, signals=["stac"], views=("whole",))
    g = result["groups"]["jepa:jepa.pt"]
    assert g["episodes"]["slip"]["failures"] == 24 and g["episodes"]["slip"]["twin_failed_too"] == 12
    whole = g["views"]["whole"]
    assert whole["ranking"]["slip"]["stac"]["failures"] == 12 and whole["ranking"]["slip"]["stac"]["auroc"] == 1.0
    d = single(whole, "fast", "stac")["slip"]
    assert d["failures"] == 12 and d["true_alerts"] == 12 and d["prompt_alerts"] == 12
    assert d["shared_failures"] == 12      # read beside (their alerts too), never as catches or misses
    gone = single(whole, "fast", "stac")["never_mattered"]
    assert gone["failures"] == 0 and gone["tpr"] is None and gone["balanced_accuracy"] is None
    changed = single(whole, "fast", "stac")["changed_how"]
    assert changed["failures"] == 0 and changed["shared_failures"] == changed["shared_failure_alerts"] == 6
    late = single(whole, "fast", "stac")["too_late"]
    assert late["regime_successes"] == 4 and g["episodes"]["too_late"]["ended_before_onset"] == 4
    text = cmp.summary_text(result)
    assert "slip 24 (24 failed, 12 of them as their natural twin did: not counted as the fault's)" in text
    assert "too_late 8 (0 failed; 4 ended before the onset)" in text
    (row,) = [r for r in cmp.detection_table(result, "whole", "fast", "changed_how") if r.startswith("| stac band |")]
    assert row.endswith("| 6/6=1.00 |")
    # a seed recorded twice without the fault, once failing: the fault cannot be said to have made the difference,
    # whichever copy was read first
    reroll = natural()[1:2]
    reroll[0]["success"], reroll[0]["length"] = False, 300
    for both in (rows + reroll, reroll + rows):
        twice = run(both, signals=["stac"], views=("whole",))
        assert twice["groups"]["jepa:jepa.pt"]["episodes"]["slip"]["twin_failed_too"] == 13     # seed 1 joins them
    # without the natural episodes nobody knows what the twin did: every failure counts, as before
    alone = run([r for r in rows if r["regime"] != "natural"] + natural()[:2], signals=["stac"], views=("whole",))
    slip = alone["groups"]["jepa:jepa.pt"]["episodes"]["slip"]
    assert slip["twin_failed_too"] == 1 and slip["no_twin"] == 22     # only seeds 0 and 1 have twins; 0 failed
    assert "22 without a natural twin in the records: counted as the fault's" in cmp.summary_text(alone)


def test_the_goal_as_written_holds_at_its_edges():
    """Balanced accuracy >= 0.90 and a median delay <= PROMPT_DECISIONS: both bounds included."""
    def figures(bacc, delay):
        return {"balanced_accuracy": bacc, "delay_decisions": None if delay is None else {"median": delay}}
    assert cmp.meets_goal(figures(0.90, 2.0)) and cmp.meets_goal(figures(1.0, 0.0))
    assert not cmp.meets_goal(figures(0.8999, 1.0)) and not cmp.meets_goal(figures(0.95, 2.01))
    assert not cmp.meets_goal(figures(None, 1.0)) and not cmp.meets_goal(figures(0.95, None))


def test_a_fault_whose_onset_comes_after_the_prefix_is_named_so_and_not_ranked_as_a_missed_detection():
    """The prefix view keeps the first decisions only. A fault whose onset (env step 30) comes after the last score
    known there (3 decisions at steps 0, 8, 16; STAC known at the step, NMSE at step + 4 = 20) cannot be caught there
    by any detector: the count says so and the summary prints that, not a best detector at chance. The whole view
    still catches it."""
    rows = natural()
    rows += faulted(kept(12), "late", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    # onset at step 10: inside a 3-decision prefix
    rows += [record(s, False, 38, "early", 10, stac=lambda i, st, g: 5 + g.random() if st > 10 else g.random())
             for s in kept(12)]
    # half of them late: onset 10 on 6 seeds, 30 on 6 others
    rows += [record(s, False, 38, "mixed", 10 if k < 6 else ONSET,
                    stac=lambda i, st, g, o=10 if k < 6 else ONSET: 5 + g.random() if st > o else g.random())
             for k, s in enumerate(kept(12))]
    result = run(rows, signals=["stac"], prefix=3)
    v = result["groups"]["jepa:jepa.pt"]["views"]
    prefix = single(v["prefix"], "fast", "stac")
    assert (prefix["late"]["onset_after_view"], prefix["early"]["onset_after_view"]) == (12, 0)
    assert prefix["mixed"]["onset_after_view"] == 6
    assert single(v["whole"], "fast", "stac")["late"]["onset_after_view"] == 0
    assert single(v["whole"], "fast", "stac")["late"]["true_alerts"] == 12
    text = cmp.summary_text(result)
    prefix_text, whole_text = text[:text.index("  whole (")], text[text.index("  whole ("):]
    assert ("[fast] late             the onset comes after the last score known in this view in all 12 failures: no "
            "detector can catch them here (see the whole view)") in prefix_text
    assert "late             best" not in prefix_text and "early            best" in prefix_text
    assert "the last score known in this view in 6 of them" in prefix_text
    assert "onset comes after" not in whole_text
    assert "the last score known in this view in all 12 failures" in cmp.markdown(result)
    assert "The onset comes after the last score known in this view in 12 of these failures" in \
        "\n".join(cmp.detection_table(result, "prefix", "fast", "late"))


@pytest.mark.parametrize("signal, onset, late", [("nmse", 19, 0), ("nmse", 20, 12), ("stac", 15, 0),
                                                  ("stac", 16, 12), ("stac", 18, 12)])
def test_the_onset_after_the_view_is_counted_against_the_last_score_the_chosen_signals_know(signal, onset, late):
    """A 3-decision prefix: decisions at env steps 0, 8, 16; NMSE known at step + 4 (20), STAC at the step (16). An
    alert counts when known after the onset, so an onset at 19 can still be caught by NMSE and one at 20 cannot;
    with STAC alone an onset at 18 cannot, though NMSE (not chosen) is known later."""
    def rise(i, s, g):
        return 5 + g.random() if s + (4 if signal == "nmse" else 0) > onset else g.random()
    rows = natural() + [record(s, False, 38, "shift", onset, **{signal: rise}) for s in kept(12)]
    d = single(run(rows, signals=[signal], prefix=3)["groups"]["jepa:jepa.pt"]["views"]["prefix"], "fast",
               signal)["shift"]
    assert d["onset_after_view"] == late
    if late:
        assert d["true_alerts"] == 0
    else:
        assert d["true_alerts"] >= 10      # the last decision lights up after the onset


def test_a_direct_caller_who_skips_the_twin_matching_gets_an_error_not_every_faulted_failure_counted():
    eps = [cmp.episode_of(r) for r in natural(12) + faulted(kept(3), "slip", None) + faulted([0], "slip", None)]
    with pytest.raises(ValueError, match="mark_twin_outcomes"):
        cmp.ranking(eps, ["stac"], "slip", None, 50, 0)
    cmp.mark_twin_outcomes(eps)
    assert cmp.ranking(eps, ["stac"], "slip", None, 50, 0)["stac"]["failures"] == 3   # seed 0's twin failed too


def test_the_demo_report_names_a_fault_no_detector_can_catch_in_the_prefix():
    """``jepa-demo``'s report table reads the same rows: a fault whose onset lies beyond the prefix gets a line
    that says so, not a best detector at chance."""
    from jepa_policy.demo.report import failure_report_lines
    rows = natural() + faulted(kept(12), "late", lambda i, s, g: 5 + g.random() if s > ONSET else g.random())
    result = run(rows, signals=["stac"], prefix=3, rule_names=("default",))
    lines, _ = failure_report_lines({"result": result, "episodes": len(rows), "train_seed": 42,
                                     "natural_episodes": 90, "seed_block": 0, "fault_episodes": 12,
                                     "faults": ["late"]})
    page = "\n".join(lines)
    assert ("| jepa | late | prefix | none can catch these: the onset comes after the last score known in this view "
            "in all 12 failures |") in page
    assert "| jepa | late | whole | " in page and "| jepa | late | prefix | stac" not in page
