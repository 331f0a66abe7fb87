"""``jepa-policy`` smoke paths: describe --json, bench with tiny counts, train -> eval -> protocols."""
import json
import re

import numpy as np

import pytest

from jepa_policy.cli import main


def test_describe_json_prints_paper_counts(capsys):
    assert main(["describe", "--task", "ToolHang", "--arm", "jepa", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["arm"] == "jepa" and abs(report["total"] / 43.96e6 - 1) < 0.02
    assert report["parts"]


def test_bench_latency_counts_passes(capsys):
    assert main(["bench", "latency", "--task", "PushT", "--arms", "mip,jepa,diffusion", "--warmup", "1",
                 "--iters", "2", "--dp-steps", "5,2", "--device", "cpu", "--json"]) == 0
    printed, err = capsys.readouterr()
    result = json.loads(printed)
    assert "bench latency: 100%" in err and "3/3" in err      # 1 warm-up + 2 timed rounds
    arms = result["arms"]
    assert set(arms) == {"mip", "jepa", "jepa+monitor", "diffusion-5", "diffusion-2"}
    for label in ("mip", "jepa", "jepa+monitor"):
        assert arms[label]["passes"]["encoder"] == 1 and arms[label]["network_passes"] == 2
    assert arms["jepa"]["passes"]["future_head"] == 1          # the control pass skips the future head
    assert arms["jepa+monitor"]["passes"]["future_head"] == 2
    assert "future_head" not in arms["mip"]["passes"]
    assert arms["diffusion-5"]["passes"]["denoiser"] == 5 and arms["diffusion-2"]["network_passes"] == 2
    assert {"jepa_over_mip", "dp5_over_jepa", "dp2_over_jepa"} <= set(result["ratios"])
    assert all(row["mean_ms"] > 0 and row["p95_ms"] >= row["median_ms"] for row in arms.values())


def test_bench_latency_times_the_failure_scores_beside_the_same_arm(capsys):
    assert main(["bench", "latency", "--task", "PushT", "--preset", "quick", "--arms", "mip,jepa", "--warmup", "1",
                 "--iters", "2", "--device", "cpu", "--scores", "--json", "--no-progress"]) == 0
    printed, err = capsys.readouterr()
    result = json.loads(printed)
    assert "bench latency" not in err
    arms = result["arms"]
    assert result["preset"] == "quick" and arms["jepa"]["params_m"] < 1     # the quick preset's shapes
    labels = ("mip", "jepa", "jepa+monitor")
    assert set(arms) == {*labels, *(f"{x} runtime" for x in labels), *(f"{x} runtime+scores" for x in labels)}
    for label in labels:
        assert arms[f"{label} runtime+scores"]["passes"] == arms[label]["passes"]      # the same network passes
        ratio = result["ratios"][f"{label}+scores_over_{label}"]
        assert ratio == arms[f"{label} runtime+scores"]["mean_ms"] / arms[f"{label} runtime"]["mean_ms"]


def test_bench_train_reports_throughput_and_memory(capsys):
    assert main(["bench", "train", "--task", "PushT", "--preset", "quick", "--steps", "1", "--warmup", "0",
                 "--device", "cpu", "--json"]) == 0
    printed, err = capsys.readouterr()
    result = json.loads(printed)
    assert "bench train: 100%" in err
    assert result["batch_size"] == 8 and result["image_size"] == 32
    assert result["samples_per_s"] > 0 and result["peak_rss_mib"] > 0


def test_bench_rollouts_prints_its_plan_an_estimate_and_a_progress_bar(capsys):
    """Square's default ran ~3.5 minutes in silence: the plan, the expected time and a bar of episodes go to
    stderr (stdout keeps the result line); --no-progress keeps stderr clean."""
    argv = ["bench", "rollouts", "--task", "PushT", "--workers", "1", "--episodes", "3", "--num-envs", "2",
            "--max-steps", "10", "--repeats", "1"]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    lines = err.replace("\r", "\n").splitlines()
    assert lines[0] == ("bench rollouts: PushT at 48 px, 2 timed evaluations (1 each with 0, 1 workers) of 3 episodes "
                        "of <= 10 steps in rounds of 2: up to 60 env steps (the worker pools start first)")
    assert re.fullmatch(r"pools started in [\d.]+ s; one PushT step takes [\d.]+ ms in a worker, so the evaluations "
                        r"take about [\d.]+ min of env time \(plus the policy's\)", lines[1])
    assert any(re.match(r"PushT rollouts: 100%.* 6/6 ", line) for line in lines), err   # 2 evaluations x 3 episodes
    assert out.startswith("PushT rollouts (3 episodes of <= 10 steps") and "records identical: True" in out
    assert main(argv + ["--no-progress"]) == 0
    assert capsys.readouterr().err == ""


def test_train_eval_protocols_from_the_command_line(pusht_demo_file, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--task", "PushT", "--preset", "quick", "--dataset", str(pusht_demo_file),
                 "--steps", "4", "--warmup-steps", "1", "--eval-every", "2", "--eval-episodes", "1",
                 "--eval-workers", "1", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["step"] == 4 and [p["step"] for p in summary["eval_curve"]] == [2, 4]
    logged = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [(row["eval_workers"], row["eval_reruns"]) for row in logged if "eval_workers" in row] == [(1, [])] * 2
    ckpt = out / "checkpoints" / "latest.pt"
    assert main(["eval", "--checkpoint", str(ckpt), "--episodes", "2", "--seed", "3", "--num-envs", "2",
                 "--max-steps", "10", "--workers", "2", "--out", str(tmp_path / "eval.jsonl")]) == 0
    printed, err = capsys.readouterr()
    report = json.loads(printed)
    assert "eval: 100%" in err and "2/2" in err     # README's 40 episodes ran 300 s in silence before the bar
    assert report["episodes"] == 2 and 0.0 <= report["success_rate"] <= 1.0
    assert report["workers"] == 2 and report["reruns"] == []
    assert report["renderer"] == "none"   # PushT rasterises without OpenGL; MuJoCo tasks name their backend
    plain = [json.loads(line) for line in (tmp_path / "eval.jsonl").read_text().splitlines()]
    assert len(plain) == 2   # named, so that compare never pools two checkpoints' records as one policy
    assert {(r["arm"], r["checkpoint"]) for r in plain} == {("jepa", str(ckpt))}
    # the trained policy's own rollouts timed: its task and size, the same episodes (seeds 3, 4) as eval ran
    assert main(["bench", "rollouts", "--checkpoint", str(ckpt), "--workers", "1", "--episodes", "2",
                 "--num-envs", "2", "--max-steps", "10", "--repeats", "1", "--seed", "3", "--json",
                 "--no-progress"]) == 0
    timed = json.loads(capsys.readouterr().out)
    assert (timed["task"], timed["image_size"], timed["checkpoint"]) == ("PushT", 32, str(ckpt))   # quick: 32 px
    assert timed["identical_records"] and timed["successes"] == sum(r["success"] for r in plain)
    assert timed["mean_length"] == np.mean([r["length"] for r in plain])
    # faults only, one of them twice under labels: the records are tagged with the labels, no natural block
    assert main(["eval", "--checkpoint", str(ckpt), "--episodes", "2", "--seed", "3", "--max-steps", "10",
                 "--workers", "0", "--faults", "sensor_noise;sensor_noise:std=9,label=noisier", "--faults-only",
                 "--out", str(tmp_path / "faults.jsonl"), "--no-progress"]) == 0
    printed, err = capsys.readouterr()
    assert list(json.loads(printed)["regimes"]) == ["sensor_noise", "noisier"]
    assert "eval:" not in err and "[eval] noisier: 2 episodes" in err     # the regime lines stay, the bar goes
    rows = [json.loads(line) for line in (tmp_path / "faults.jsonl").read_text().splitlines()]
    assert [r["regime"] for r in rows] == ["sensor_noise"] * 2 + ["noisier"] * 2
    assert [r["seed"] for r in rows] == [3, 4] * 2
    assert main(["eval", "--checkpoint", str(ckpt), "--faults", "sensor_noise;sensor_noise:std=9"]) == 2
    assert "label=" in capsys.readouterr().err
    assert main(["audit", "--checkpoint", str(ckpt), "--dataset", str(pusht_demo_file), "--samples", "64",
                 "--pool", "16", "--permutations", "50", "--batches", "2"]) == 0
    printed, err = capsys.readouterr()
    audit = json.loads(printed)
    assert all(f"{name} audit: 100%" in err for name in ("collapse", "retrieval", "gradient")), err
    views = audit["collapse"]["views"]
    assert audit["collapse"]["samples"] == 64 and list(views) == ["c_t", "e_rgb", "z_hat"]
    assert views["c_t"]["dim"] == 32 and views["e_rgb"]["dim"] == views["z_hat"]["dim"] == 8 * 8   # width 32
    assert "fused representation" in views["c_t"]["what"] and "E_rgb" in views["e_rgb"]["what"]
    assert 1.0 <= views["e_rgb"]["effective_rank"] <= 64 and 0.0 <= views["e_rgb"]["te32"] <= 1.0
    assert audit["retrieval"]["all"]["pool"] == 16 and audit["retrieval"]["all"]["queries"] == 64
    assert set(audit["gradients"]["groups"]) == {"encoder", "conditioning", "action_head", "future_head", "trunk"}
    for source in (out / "eval_curve.json", ckpt):
        assert main(["protocols", str(source)]) == 0
        protocols = json.loads(capsys.readouterr().out)
        assert protocols["evaluations"] == 2 and set(protocols) >= {"best", "mean_last5", "mean_all", "last"}


def test_unknown_option_is_rejected():
    with pytest.raises(SystemExit):
        main(["train", "--stepz", "3"])


def test_every_flag_of_every_subcommand_has_help():
    import argparse

    from jepa_policy.cli import build_parser

    def parsers(p):
        yield p
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from parsers(sub)

    missing = [f"{p.prog} {a.option_strings or a.dest}" for p in parsers(build_parser()) for a in p._actions
               if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) and not a.help]
    assert missing == []


@pytest.mark.parametrize("args, message", [
    (["train", "--preset", "quick", "--steps", "1", "--warmup-steps", "2"], "steps (1) is below warmup_steps (2)"),
    (["train", "--preset", "quick", "--dataset", "/nonexistent/demos.hdf5"], "/nonexistent/demos.hdf5 does not exist"),
    (["train", "--preset", "quick", "--arm", "jepa2", "--dataset", "x.hdf5"], "arm='jepa2' is unknown"),
    (["train", "--task", "Nope"], "unknown task 'Nope'"),
    (["train", "--config", "/nonexistent/train_config.json"], "--config /nonexistent/train_config.json does not exist"),
    (["eval", "--checkpoint", "/nonexistent.pt"], "/nonexistent.pt does not exist"),
    (["eval", "--checkpoint", "/nonexistent.pt", "--faults-only"], "--faults-only needs --faults"),
    (["protocols", "/nonexistent"], "/nonexistent does not exist; pass a run's eval_curve.json"),
])
def test_user_errors_are_one_line_and_exit_2(args, message, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_documented_resume_of_a_stopped_run_goes_on_to_the_end(pusht_demo_file, tmp_path, capsys):
    """`--config RUN/train_config.json --resume RUN/checkpoints/latest.pt` after --stop-at: trains on, says so."""
    run = tmp_path / "run"
    assert main(["train", "--task", "PushT", "--preset", "quick", "--dataset", str(pusht_demo_file), "--steps", "6",
                 "--warmup-steps", "1", "--stop-at", "3", "--out", str(run), "--no-progress"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["step"] == 3
    assert json.loads((run / "train_config.json").read_text())["stop_at"] == 3
    assert main(["train", "--config", str(run / "train_config.json"), "--resume",
                 str(run / "checkpoints" / "latest.pt")]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out.strip().splitlines()[-1])["step"] == 6
    assert "at step 3: training to step 6 of 6" in captured.err
    assert main(["train", "--config", str(run / "train_config.json"), "--resume",
                 str(run / "checkpoints" / "latest.pt"), "--stop-at", "4"]) == 2
    assert "stop_at 4 is not after the checkpoint's step 6" in capsys.readouterr().err


def test_fault_options_take_json_lists_with_commas():
    """``--faults`` splits a fault's options at commas outside brackets: its own help's onset=[20,60] and an RGB
    tint are lists; a broken list is a one-line error."""
    from jepa_policy.cli import _fault_spec

    assert _fault_spec("background_tint:tint=[-4,-1,3],onset=[20,60]") == {
        "name": "background_tint", "tint": [-4, -1, 3], "onset": [20, 60]}
    assert _fault_spec("action_noise:std=40, onset=30") == {"name": "action_noise", "std": 40, "onset": 30}
    with pytest.raises(ValueError, match="not a number or JSON list"):
        _fault_spec("block_displaced:onset=[20")


@pytest.mark.timeout(300)
def test_bench_serve_measures_the_server_beside_in_process_decisions(capsys):
    """The server's benchmark (jepa_policy/serve/bench.py) end to end on a random-weight PushT quick model: the
    overhead phase and one concurrency level per batching setting, each phase on the bar."""
    assert main(["bench", "serve", "--preset", "quick", "--iters", "3", "--seconds", "0.5", "--clients", "1",
                 "--json"]) == 0
    printed, err = capsys.readouterr()
    result = json.loads(printed)
    assert result["overhead"]["served_p50_ms"] > 0 and result["overhead"]["in_process_p50_ms"] > 0
    assert set(result["concurrency"]) == {"batch16_clients1", "batch1_clients1"}
    assert all(row["decisions_per_s"] > 0 for row in result["concurrency"].values())
    assert "bench serve: 100%" in err and "3/3" in err
