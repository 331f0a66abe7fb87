"""Training loop: configs, schedule, overfitting a tiny real dataset, exact resume, logs."""
import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_envs.tasks.spec import all_task_specs
from jepa_policy.checkpoint import load_checkpoint
from jepa_policy.train import TrainConfig, cosine_with_warmup, load_config, train


@pytest.fixture(scope="module")
def demos(pusht_demo_file):
    return load_dataset(pusht_demo_file, task="PushT", image_size=32)


def test_every_task_has_validated_presets():
    sim = [s for s in all_task_specs() if s.suite in ("embedded", "robomimic", "libero", "mimicgen")]
    assert len(sim) == 13  # PushT, PushTStandard + the paper's nine simulated tasks + robomimic's Lift and Can
    for spec in sim:
        paper = load_config(spec.name, "paper")
        assert (paper.steps, paper.batch_size, paper.lr, paper.ema_decay) == (300_000, 256, 1e-4, 0.995)
        assert paper.eval_every == 10_000 and paper.eval_episodes == 40
        load_config(spec.name, "cpu")
    quick = load_config("PushT", "quick", steps=7)
    assert quick.steps == 7 and quick.model["width"] == 32


def test_config_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown training option"):
        TrainConfig.from_dict({"stepz": 3})
    with pytest.raises(TypeError, match="'steps' must be int"):
        TrainConfig.from_dict({"steps": "many"})
    with pytest.raises(KeyError, match="no preset 'huge'"):
        load_config("PushT", "huge")
    with pytest.raises(ValueError, match="unknown override"):
        load_config("PushT", "quick", model={"widht": 8})
    with pytest.raises(ValueError, match="grad_accum"):
        load_config("PushT", "quick", grad_accum=3)


def test_cosine_schedule_with_warmup_follows_its_formula():
    p = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([p], lr=1e-3)
    sched = cosine_with_warmup(opt, warmup_steps=4, total_steps=20)
    lrs = []
    for _ in range(20):
        lrs.append(sched.get_last_lr()[0])
        opt.step()
        sched.step()
    expected = [1e-3 * (0.25 + 0.75 * s / 4) for s in range(4)]
    expected += [1e-3 * 0.5 * (1 + math.cos(math.pi * (s - 4) / 16)) for s in range(4, 20)]
    np.testing.assert_allclose(lrs, expected, rtol=1e-6)


def test_tiny_model_overfits_tiny_pusht_dataset(demos, tmp_path):
    n = 16  # the first 16 steps of one expert demo
    small = dataclasses.replace(demos, obs={k: v[:n] for k, v in demos.obs.items()}, actions=demos.actions[:n],
                                episode_ends=np.array([n]))
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path), steps=300, log_every=1, warmup_steps=10,
                      model={"width": 64, "layers": 2, "heads": 2})
    hist = train(cfg, small)["history"]
    first = {k: np.mean([h[k] for h in hist[:5]]) for k in ("loss", "loss_act_step0", "loss_future")}
    last = {k: np.mean([h[k] for h in hist[-20:]]) for k in ("loss", "loss_act_step0", "loss_future")}
    assert last["loss"] < first["loss"] / 20
    assert last["loss_future"] < first["loss_future"] / 100
    assert last["loss_act_step0"] < first["loss_act_step0"] / 2


def test_resume_reproduces_the_uninterrupted_run_exactly(demos, tmp_path):
    opts = dict(steps=8, log_every=1, warmup_steps=2, batch_size=8, model={"dropout": 0.1})
    full = train(load_config("PushT", "quick", out_dir=str(tmp_path / "full"), **opts), demos)
    part = load_config("PushT", "quick", out_dir=str(tmp_path / "part"), stop_at=3, **opts)
    first = train(part, demos)
    assert first["step"] == 3
    ckpt3 = load_checkpoint(first["checkpoint"])
    assert ckpt3["step"] == 3 and ckpt3["sampler"]["batches_taken"] + ckpt3["sampler"]["epoch"] >= 1
    resumed = train(dataclasses.replace(part, stop_at=0, resume=first["checkpoint"]), demos)
    assert resumed["step"] == 8
    a, b = load_checkpoint(full["checkpoint"]), load_checkpoint(resumed["checkpoint"])
    for part_name in ("model", "ema"):
        assert a[part_name].keys() == b[part_name].keys()
        for key in a[part_name]:
            assert torch.equal(a[part_name][key], b[part_name][key]), (part_name, key)
    assert [h["loss"] for h in full["history"][3:]] == [h["loss"] for h in resumed["history"]]
    # EMA weights are a real average: they differ from the raw weights after training
    assert not torch.equal(a["model"]["action_head.weight"], a["ema"]["module.action_head.weight"])
    # logs: JSONL rows for every step of both runs, TensorBoard events, the config beside them
    rows = [json.loads(line) for line in (tmp_path / "part" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, 9))
    assert list((tmp_path / "part" / "tensorboard").glob("events.out.tfevents.*"))
    assert json.loads((tmp_path / "part" / "train_config.json").read_text())["stop_at"] == 0


def test_resume_with_more_steps_continues_one_cosine_to_the_new_end(demos, tmp_path, capsys):
    """Resuming a finished 6-step run with --steps 12 kept the 6-step cosine: lr 0 at step 6, then back
    up to the peak at step 12. Now it follows the schedule of a run launched with 12 steps, bit for bit."""
    opts = dict(log_every=1, warmup_steps=2, batch_size=8)
    short = train(load_config("PushT", "quick", out_dir=str(tmp_path / "short"), steps=6, **opts), demos)
    capsys.readouterr()
    longer = train(load_config("PushT", "quick", out_dir=str(tmp_path / "short"), steps=12,
                               resume=short["checkpoint"], **opts), demos)
    assert "one cosine schedule now ends at step 12, as in a run launched with --steps 12" in capsys.readouterr().err
    launched = train(load_config("PushT", "quick", out_dir=str(tmp_path / "long"), steps=12, **opts), demos)
    resumed_lr = [h["lr"] for h in longer["history"]]
    assert [h["step"] for h in longer["history"]] == list(range(7, 13))
    assert resumed_lr == [h["lr"] for h in launched["history"][6:]]
    after_warmup = [h["lr"] for h in launched["history"][1:]]
    assert all(a >= b for a, b in zip(after_warmup, after_warmup[1:])) and resumed_lr[-1] == pytest.approx(0, abs=1e-12)
    assert resumed_lr[0] > 0.4e-3        # the new schedule's lr at step 7, not the old one's 0 climbing back
    # the same length keeps the checkpoint's own schedule (exact resume, tested above); a shorter one is refused
    with pytest.raises(ValueError, match="--steps 4 ends before the checkpoint's step 12"):   # its latest.pt now
        train(load_config("PushT", "quick", out_dir=str(tmp_path / "short"), steps=4, resume=short["checkpoint"],
                          **opts), demos)


def test_train_rejects_dataset_of_another_task(demos, tmp_path):
    with pytest.raises(ValueError, match="dataset is for task 'PushT'"):
        train(load_config("Square", "cpu", out_dir=str(tmp_path), steps=1, warmup_steps=0), demos)
    with pytest.raises(ValueError, match="make-demos"):
        train(load_config("PushT", "quick", out_dir=str(tmp_path), steps=1, warmup_steps=0))


def test_best_of_k_start_continues_the_lowest_loss_candidate_exactly(demos, tmp_path):
    opts = dict(steps=8, log_every=1, warmup_steps=2, batch_size=8, seed=5)
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path / "best"), init_candidates=3, init_screen_steps=3,
                      **opts)
    result = train(cfg, demos)
    sel = result["init_selection"]
    assert sel["seeds"] == [5, 10_005, 20_005] and sel["score_steps"] == [3, 3]
    assert sel["score_on"] == "loss_act_step0"
    # each score is the candidate's own logged training loss over the scored steps, and the lowest one won
    for seed, score in zip(sel["seeds"], sel["scores"]):
        rows = [json.loads(line) for line in
                (tmp_path / "best" / "init_candidates" / f"seed{seed}" / "log.jsonl").read_text().splitlines()]
        assert [r["step"] for r in rows] == [1, 2, 3]
        assert score == pytest.approx(rows[2]["loss_act_step0"], rel=1e-6)
    assert len(set(sel["scores"])) == 3
    assert sel["chosen_seed"] == sel["seeds"][int(np.argmin(sel["scores"]))]
    assert json.loads((tmp_path / "best" / "init_selection.json").read_text()) == sel
    # the result is the plain run of the chosen seed, to the bit, with one learning curve from step 1
    plain = train(load_config("PushT", "quick", out_dir=str(tmp_path / "plain"),
                              **{**opts, "seed": sel["chosen_seed"]}), demos)
    a, b = load_checkpoint(result["checkpoint"]), load_checkpoint(plain["checkpoint"])
    assert a["step"] == 8 and a["init_selection"] == sel and b["init_selection"] is None
    for key in a["ema"]:
        assert torch.equal(a["ema"][key], b["ema"][key]), key
    rows = [json.loads(line) for line in (tmp_path / "best" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, 9))
    assert [r["loss"] for r in rows] == [h["loss"] for h in plain["history"]]
    # a later resume of the selected run keeps the chosen seed (stop at 6, then continue to 8)
    part = train(dataclasses.replace(cfg, out_dir=str(tmp_path / "part"), stop_at=6), demos)
    assert part["step"] == 6
    rest = train(dataclasses.replace(cfg, out_dir=str(tmp_path / "part"), resume=part["checkpoint"]), demos)
    c = load_checkpoint(rest["checkpoint"])
    assert c["init_selection"]["chosen_seed"] == sel["chosen_seed"]
    for key in a["ema"]:
        assert torch.equal(a["ema"][key], c["ema"][key]), key


def test_best_of_k_start_options_are_checked():
    with pytest.raises(ValueError, match="init_screen_steps must be in"):
        load_config("PushT", "quick", steps=10, init_candidates=2, init_screen_steps=10)
    with pytest.raises(ValueError, match="init_candidates must be >= 1"):
        load_config("PushT", "quick", init_candidates=0)
    with pytest.raises(ValueError, match="stop_at must be 0 or after init_screen_steps"):
        load_config("PushT", "quick", steps=10, init_candidates=2, init_screen_steps=4, stop_at=3)


def test_pretrained_backbone_is_loaded_frozen_and_recorded(demos, tmp_path):
    from jepa_policy.checkpoint import BACKBONE

    opts = dict(steps=3, warmup_steps=0, batch_size=4, model={"width": 32, "layers": 1, "heads": 2})
    source = train(load_config("PushT", "quick", out_dir=str(tmp_path / "a"), seed=1, **opts), demos)["checkpoint"]
    frozen = load_config("PushT", "quick", out_dir=str(tmp_path / "b"), seed=2, **{
        **opts, "model": {**opts["model"], "encoder_weights": source, "freeze_encoder": True}})
    result = load_checkpoint(train(frozen, demos)["checkpoint"])
    src = load_checkpoint(source)
    backbone = [k for k in result["model"] if k.startswith(BACKBONE)]
    assert backbone and all(torch.equal(result["model"][k], src["ema"]["module." + k]) for k in backbone)
    assert not torch.equal(result["model"]["encoder.fuse.0.weight"], src["ema"]["module.encoder.fuse.0.weight"])
    cfg = result["model_config"]
    assert cfg["encoder_weights"] == source and cfg["freeze_encoder"] and len(cfg["encoder_weights_sha256"]) == 64
    # fine-tuning from the same weights moves them; a file that does not fit says why
    tuned = load_config("PushT", "quick", out_dir=str(tmp_path / "c"), **{
        **opts, "model": {**opts["model"], "encoder_weights": source}})
    moved = load_checkpoint(train(tuned, demos)["checkpoint"])["model"]
    assert any(not torch.equal(moved[k], src["ema"]["module." + k]) for k in backbone)
    wrong = load_config("PushT", "quick", out_dir=str(tmp_path / "d"), **{
        **opts, "model": {**opts["model"], "encoder_width": 16, "encoder_weights": source}})
    with pytest.raises(ValueError, match="does not fit this model's image backbone"):
        train(wrong, demos)
    with pytest.raises(ValueError, match="freeze_encoder needs encoder_weights"):
        load_config("PushT", "quick", model={"freeze_encoder": True})


def test_gradient_interaction_is_logged_without_changing_the_run(demos, tmp_path):
    opts = dict(steps=4, warmup_steps=0, batch_size=4, log_every=2, model={"width": 32, "layers": 1, "heads": 2})
    logged = train(load_config("PushT", "quick", out_dir=str(tmp_path / "a"), grad_every=2, **opts), demos)
    plain = train(load_config("PushT", "quick", out_dir=str(tmp_path / "b"), grad_every=0, **opts), demos)
    rows = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    grads = [r for r in rows if "gradient_interaction" in r]
    assert [r["step"] for r in grads] == [2, 4]
    assert set(grads[0]["gradient_interaction"]["groups"]) == {"encoder", "conditioning", "action_head",
                                                               "future_head", "trunk"}
    a, b = load_checkpoint(logged["checkpoint"]), load_checkpoint(plain["checkpoint"])
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])


def test_snapshots_without_evaluation_keep_the_ema_weights_for_a_later_curve(demos, tmp_path):
    """eval_episodes 0: every eval_every steps the EMA weights are kept (eval_stepN.pt) and nothing is rolled out
    during training; the last snapshot holds the final EMA weights."""
    from jepa_policy.policy import Policy
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path), steps=6, warmup_steps=1, eval_every=3,
                      eval_episodes=0)
    run = train(cfg, demos)
    assert run["curve"] == []
    snapshots = sorted(p.name for p in (tmp_path / "checkpoints").glob("eval_step*.pt"))
    assert snapshots == ["eval_step3.pt", "eval_step6.pt"]
    last = Policy.from_checkpoint(tmp_path / "checkpoints" / "eval_step6.pt")
    final = Policy.from_checkpoint(tmp_path / "checkpoints" / "latest.pt")
    for a, b in zip(last.model.state_dict().values(), final.model.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="needs keep_eval_checkpoints"):
        load_config("PushT", "quick", eval_every=3, eval_episodes=0, keep_eval_checkpoints=False)


def test_tqdms_own_switch_silences_the_training_bar(demos, tmp_path, monkeypatch, capsys):
    """jepa-demo --no-progress sets TQDM_DISABLE for the processes it spawns; the training bar, whose disable
    is passed explicitly (so tqdm itself would ignore the variable), obeys it too."""
    opts = dict(steps=2, log_every=1, warmup_steps=0, batch_size=4, progress=True)
    train(load_config("PushT", "quick", out_dir=str(tmp_path / "on"), **opts), demos)
    assert "PushT/jepa" in capsys.readouterr().err
    monkeypatch.setenv("TQDM_DISABLE", "1")
    train(load_config("PushT", "quick", out_dir=str(tmp_path / "off"), **opts), demos)
    assert "PushT/jepa" not in capsys.readouterr().err
