"""``jepa-policy`` smoke paths: describe --json, bench with tiny counts, train -> eval -> protocols."""
import json

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
    result = json.loads(capsys.readouterr().out)
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


def test_bench_train_reports_throughput_and_memory(capsys):
    assert main(["bench", "train", "--task", "PushT", "--preset", "quick", "--steps", "1", "--warmup", "0",
                 "--device", "cpu", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["batch_size"] == 8 and result["image_size"] == 32
    assert result["samples_per_s"] > 0 and result["peak_rss_mib"] > 0


def test_train_eval_protocols_from_the_command_line(pusht_demo_file, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--task", "PushT", "--preset", "quick", "--dataset", str(pusht_demo_file),
                 "--steps", "4", "--warmup-steps", "1", "--eval-every", "2", "--eval-episodes", "1",
                 "--out-dir", str(out), "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["step"] == 4 and [p["step"] for p in summary["eval_curve"]] == [2, 4]
    ckpt = out / "checkpoints" / "latest.pt"
    assert main(["eval", "--checkpoint", str(ckpt), "--episodes", "2", "--seed", "3", "--num-envs", "2",
                 "--max-steps", "10", "--out", str(tmp_path / "eval.jsonl")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["episodes"] == 2 and 0.0 <= report["success_rate"] <= 1.0
    assert len((tmp_path / "eval.jsonl").read_text().splitlines()) == 2
    assert main(["audit", "--checkpoint", str(ckpt), "--dataset", str(pusht_demo_file), "--samples", "64"]) == 0
    audit = json.loads(capsys.readouterr().out)
    assert audit["samples"] == 64 and audit["encoder"]["dim"] == audit["predictor"]["dim"] == 8 * 8
    assert 1.0 <= audit["encoder"]["effective_rank"] <= 64 and 0.0 <= audit["encoder"]["te32"] <= 1.0
    for source in (out / "eval_curve.json", ckpt):
        assert main(["protocols", str(source)]) == 0
        protocols = json.loads(capsys.readouterr().out)
        assert protocols["evaluations"] == 2 and set(protocols) >= {"best", "mean_last5", "mean_all", "last"}


def test_unknown_option_is_rejected():
    with pytest.raises(SystemExit):
        main(["train", "--stepz", "3"])
