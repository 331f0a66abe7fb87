"""The model family's API: config, normaliser, crops, predict, encode_future, MIP equivalence, Diffusion Policy."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from _model_helpers import make_batch, tiny_config, tiny_model, unit_stats

from jepa_policy.config import ARMS, ModelConfig
from jepa_policy.losses import two_step_loss
from jepa_policy.blocks import crop_frames, to_chw_float
from jepa_policy.model import PolicyModel, build_model

TWO_STEP_ARMS = [a for a in ARMS if a != "diffusion"]


# ----- config -----
def test_config_round_trips_through_json():
    cfg = ModelConfig.for_task("Transport", arm="dual_cross", width=192)
    again = ModelConfig.from_dict(json.loads(cfg.to_json()))
    assert again == cfg and again.cameras == cfg.cameras and again.lowdim == cfg.lowdim
    assert cfg.future_dim == 4 * 512 and cfg.lowdim_dim == 18 and cfg.action_dim == 20


def test_config_defaults_are_the_papers():
    cfg = ModelConfig.for_task("ToolHang")
    assert (cfg.width, cfg.layers, cfg.heads, cfg.tau, cfg.rho, cfg.lambda_a) == (384, 8, 6, 0.9, 0.10, 1.0)
    assert (cfg.lambda_z_mode, cfg.lambda_z_min, cfg.lambda_z_max, cfg.crop_ratio) == ("adaptive", 1e-6, 0.1, 0.9)
    assert (cfg.horizon, cfg.obs_steps, cfg.future_k, cfg.sigreg_weight) == (10, 2, 4, 0.09)
    assert cfg.cameras == ("sideview", "robot0_eye_in_hand") and cfg.crop_size == 76
    assert ModelConfig.for_task("MugMug").horizon == 16
    assert ModelConfig.for_task("ToolHang", arm="lambda_a0").lambda_z_mode == "fixed"


@pytest.mark.parametrize("changes, message", [
    (dict(arm="jepa2"), "arm='jepa2' is unknown"),
    (dict(tau=1.0), "tau=1.0"),
    (dict(width=100), "not divisible by heads"),
    (dict(arm="dual_cross", dual_future_layers=2), "must equal layers"),
    (dict(lambda_z_mode="auto"), "lambda_z_mode"),
    (dict(image_norm="imagenet"), "image_norm"),
    (dict(image_size=8), "ResNet-18 needs at least 8px"),
    (dict(diffusion_infer_steps=200), "exceeds diffusion_train_steps"),
])
def test_config_rejects_bad_values_with_a_fix(changes, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig.for_task("ToolHang", **changes)


# ----- normaliser -----
def test_normalizer_maps_min_max_to_unit_range_and_round_trips():
    model = tiny_model("mip")
    stats = unit_stats(model.cfg)
    stats["action"] = {"min": np.arange(10.0), "max": np.arange(10.0) + np.r_[np.ones(9), 0.0]}  # last dim constant
    model.set_normalizer_stats(stats)
    lo, hi = torch.tensor(stats["action"]["min"]).float(), torch.tensor(stats["action"]["max"]).float()
    assert torch.allclose(model.normalizer.normalize("action", lo)[:9], -torch.ones(9))
    assert torch.allclose(model.normalizer.normalize("action", hi)[:9], torch.ones(9))
    assert model.normalizer.normalize("action", hi)[9].item() == 0.0
    x = torch.randn(5, 10)
    assert torch.allclose(model.normalizer.unnormalize("action", model.normalizer.normalize("action", x)), x, atol=1e-5)


def pixel_stats_of(cfg, mean=(0.9, 0.8, 0.7), std=(0.1, 0.2, 0.05)) -> dict:
    stats = unit_stats(cfg)
    for key in cfg.image_keys:
        stats[key] = {"mean": np.array(mean), "std": np.array(std)}
    return stats


def test_image_standardizer_matches_the_formula_and_feeds_the_encoder():
    cfg = tiny_config("jepa", image_norm="dataset", crop_ratio=1.0)
    model = build_model(cfg).eval()
    model.set_normalizer_stats(pixel_stats_of(cfg))
    batch = make_batch(cfg)
    mean, std = torch.tensor([0.9, 0.8, 0.7])[:, None, None], torch.tensor([0.1, 0.2, 0.05])[:, None, None]
    want = {}
    for key in cfg.image_keys:
        frames = batch["obs"][key]
        got = model._pixels(key, frames)
        want[key] = (frames.movedim(-1, -3).float() / 255.0 - mean) / std
        assert got.shape == want[key].shape and torch.allclose(got, want[key], atol=1e-5)
    # The encoder sees exactly those pixels: the unit model fed the standardised frames by hand agrees.
    unit = build_model(cfg.replace(image_norm="unit")).eval()
    unit.load_state_dict(model.state_dict(), strict=False)
    unit.set_normalizer_stats(unit_stats(cfg))
    images, _, _ = model._crop_obs(batch["obs"], None, False, None)
    with torch.no_grad():
        by_hand = unit.encoder.rgb({key: x.flatten(0, 1) for key, x in want.items()})
        assert torch.allclose(model.encoder.rgb(images), by_hand, atol=1e-5)
        assert not torch.allclose(unit.encoder.rgb(unit._crop_obs(batch["obs"], None, False, None)[0]), by_hand)
    key = cfg.image_keys[0]
    # Constant channels are centred, not blown up; the unit model has no such module in its state_dict.
    model.set_normalizer_stats(pixel_stats_of(cfg, std=(0.1, 0.0, 0.05)))
    assert model.image_normalizer.fields[key].scale[1].item() == 1.0
    assert not any(k.startswith("image_normalizer") for k in unit.state_dict())


def test_image_standardizer_errors_name_the_fix_and_stats_round_trip():
    cfg = tiny_config("jepa", image_norm="dataset")
    fresh = build_model(cfg)
    with pytest.raises(ValueError, match="pixel mean/std.*normalizer_stats"):
        fresh.set_normalizer_stats(unit_stats(cfg))
    with pytest.raises(ValueError, match="expected \\(3,\\)"):
        fresh.set_normalizer_stats(pixel_stats_of(cfg, mean=(0.5, 0.5)))
    with pytest.raises(ValueError, match="finite with std >= 0"):
        fresh.set_normalizer_stats(pixel_stats_of(cfg, std=(0.1, -0.2, 0.1)))
    with pytest.raises(RuntimeError, match="set_normalizer_stats"):
        fresh.image_normalizer.normalize(cfg.image_keys[0], torch.zeros(1, 4, 4, 3))
    trained = build_model(cfg).eval()
    trained.set_normalizer_stats(pixel_stats_of(cfg))
    loaded = build_model(cfg).eval()
    loaded.load_state_dict(trained.state_dict())
    batch = make_batch(cfg)
    a1, z1 = trained.predict(batch["obs"])
    a2, z2 = loaded.predict(batch["obs"])
    assert torch.equal(a1, a2) and torch.equal(z1, z2)


def test_normalizer_errors_and_checkpoint_round_trip():
    cfg = tiny_config("jepa")
    fresh = build_model(cfg)
    batch = make_batch(cfg)
    with pytest.raises(RuntimeError, match="set_normalizer_stats"):
        fresh.predict(batch["obs"])
    with pytest.raises(ValueError, match="lack key"):
        fresh.set_normalizer_stats({"action": unit_stats(cfg)["action"]})
    bad = unit_stats(cfg)
    bad["action"]["max"] = bad["action"]["max"][:3]
    with pytest.raises(ValueError, match="expected"):
        fresh.set_normalizer_stats(bad)
    trained = tiny_model("jepa").eval()
    loaded = build_model(cfg).eval()
    loaded.load_state_dict(trained.state_dict())
    a1, z1 = trained.predict(batch["obs"])
    a2, z2 = loaded.predict(batch["obs"])
    assert torch.equal(a1, a2) and torch.equal(z1, z2)


# ----- crops -----
def test_crop_frames_uses_one_window_for_all_frames_of_a_sample():
    frames = torch.randint(0, 256, (2, 3, 10, 10, 3), dtype=torch.uint8)
    top, left = torch.tensor([0, 3]), torch.tensor([2, 1])
    out = crop_frames(frames, top, left, 7)
    for b in range(2):
        for t in range(3):
            assert torch.equal(out[b, t], frames[b, t, top[b]:top[b] + 7, left[b]:left[b] + 7])


def test_full_size_crop_returns_the_frames_unchanged():
    frames = torch.randint(0, 256, (2, 3, 10, 10, 3), dtype=torch.uint8)
    zero = torch.zeros(2, dtype=torch.long)
    out = crop_frames(frames, zero, zero, 10)
    assert torch.equal(out, frames)
    # the same values the general gather gives for a window that covers the whole frame
    ar = torch.arange(10)
    gathered = frames[torch.arange(2)[:, None, None, None], torch.arange(3)[None, :, None, None],
                      ar[None, None, :, None], ar[None, None, None, :]]
    assert torch.equal(out, gathered)


def test_training_crop_is_temporally_consistent_and_eval_crop_is_centred():
    model = tiny_model("jepa")
    cfg = model.cfg
    batch = make_batch(cfg, batch=6)
    batch["future_obs"] = {k: batch["obs"][k][:, -1].clone() for k in cfg.image_keys}   # o_{t+k} := newest frame
    seen = []
    net = model.encoder.cameras[cfg.cameras[0]]
    handle = net.register_forward_pre_hook(lambda _m, args: seen.append(args[0].detach().clone()))
    model.train()
    model.compute_loss(batch, generator=torch.Generator().manual_seed(3))
    handle.remove()
    now, future = seen[0].view(6, cfg.obs_steps, 3, cfg.crop_size, cfg.crop_size), seen[1]
    assert torch.equal(now[:, -1], future)                                     # same window for o_t and o_{t+k}
    off, size = (cfg.image_size - cfg.crop_size) // 2, cfg.crop_size
    model.eval()
    z = model.encode_future({k: batch["obs"][k][:, -1] for k in cfg.image_keys})
    z_manual = model.encoder.rgb({k: to_chw_float(batch["obs"][k][:, -1, off:off + size, off:off + size])
                                  for k in cfg.image_keys})
    assert torch.allclose(z, z_manual)                                         # encode_future: centre crop


def test_random_crops_differ_between_samples():
    model = tiny_model("jepa").train()
    cfg = model.cfg
    batch = make_batch(cfg, batch=8)
    same = {k: batch["obs"][k][:1].repeat(8, 1, 1, 1, 1) for k in cfg.image_keys}
    images, _, _ = model._crop_obs(same, None, True, torch.Generator().manual_seed(0))
    first = images[cfg.image_keys[0]].view(8, cfg.obs_steps, 3, cfg.crop_size, cfg.crop_size)
    assert any(not torch.equal(first[0], first[i]) for i in range(1, 8))


# ----- predict / encode_future -----
@pytest.mark.parametrize("arm", ARMS)
def test_predict_shapes_and_units(arm):
    model = tiny_model(arm, diffusion_infer_steps=4).eval()
    cfg = model.cfg
    batch = make_batch(cfg, batch=2)
    actions, z_hat = model.predict(batch["obs"])
    assert actions.shape == (2, cfg.horizon, cfg.action_dim) and actions.dtype == torch.float32
    assert torch.isfinite(actions).all()
    if arm in ("mip", "diffusion"):
        assert z_hat is None
    else:
        assert z_hat.shape == (2, model.future_dim) == (2, cfg.future_dim)
        assert model.predict(batch["obs"], want_future=False)[1] is None
    assert model.encode_future(batch["future_obs"]).shape == (2, model.future_dim)
    numpy_obs = {k: v.numpy() for k, v in batch["obs"].items()}
    assert model.predict(numpy_obs)[0].shape == actions.shape


@pytest.mark.parametrize("arm", TWO_STEP_ARMS)
def test_encoder_runs_once_and_the_network_twice_per_decision(arm):
    model = tiny_model(arm).eval()
    calls = {"encoder": 0, "step": 0}
    model.encoder.register_forward_hook(lambda *_: calls.__setitem__("encoder", calls["encoder"] + 1))
    step = model.step

    def counted(*args, **kwargs):
        calls["step"] += 1
        return step(*args, **kwargs)

    model.step = counted
    batch = make_batch(model.cfg, batch=2)
    first = model.predict(batch["obs"])
    assert calls == {"encoder": 1, "step": 2}
    second = model.predict(batch["obs"], want_future=False)
    assert torch.equal(first[0], second[0])              # deterministic; skipping h_z leaves actions unchanged


def test_predict_second_pass_refines_the_first():
    model = tiny_model("jepa").eval()
    cfg, b = model.cfg, 2
    batch = make_batch(cfg, batch=b)
    actions, z_hat = model.predict(batch["obs"])
    images, _, _ = model._crop_obs(batch["obs"], None, False, None)
    c = model.encoder(images, model._lowdim(batch["obs"], b).flatten(0, 1)).view(b, cfg.obs_steps, cfg.width)
    tokens = model.memory.embed_obs(c)
    t = lambda v: torch.full((b,), v)  # noqa: E731
    a0, z0 = model.step(tokens, torch.zeros(b, cfg.horizon, cfg.action_dim), torch.zeros(b, cfg.future_dim),
                        t(0.0), t(cfg.tau))
    a1, z1 = model.step(tokens, a0, z0, t(cfg.tau), t(1.0))
    assert torch.allclose(actions, model.normalizer.unnormalize("action", a1), atol=1e-5)
    assert torch.allclose(z_hat, z1, atol=1e-5)


def test_bad_observations_raise_clear_errors():
    model = tiny_model("jepa").eval()
    cfg = model.cfg
    batch = make_batch(cfg, batch=2)
    key = cfg.image_keys[0]
    with pytest.raises(KeyError, match=key):
        model.predict({k: v for k, v in batch["obs"].items() if k != key})
    with pytest.raises(ValueError, match="uint8"):
        model.predict({**batch["obs"], key: batch["obs"][key].float()})
    with pytest.raises(ValueError, match="uint8 of shape"):
        model.predict({**batch["obs"], key: batch["obs"][key][:, :1]})
    low = cfg.lowdim_keys[0]
    with pytest.raises(ValueError, match=low):
        model.predict({**batch["obs"], low: batch["obs"][low][..., :1]})
    with pytest.raises(KeyError, match="future_obs"):
        model.compute_loss({"obs": batch["obs"], "action": batch["action"]})
    with pytest.raises(ValueError, match="action"):
        model.compute_loss({**batch, "action": batch["action"][:, :3]})


# ----- training step -----
@pytest.mark.parametrize("arm", ARMS)
def test_compute_loss_reports_parts_and_backpropagates(arm):
    model = tiny_model(arm).train()
    batch = make_batch(model.cfg)
    loss, info = model.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    assert loss.dim() == 0 and torch.isfinite(loss)
    assert all(isinstance(v, float) for v in info.values()) and info["loss"] == pytest.approx(loss.item())
    loss.backward()
    if arm == "diffusion":
        return
    assert {"loss_act", "lambda_z", "loss_act_step0", "loss_act_step1"} <= set(info)
    if arm == "mip":
        assert info["lambda_z"] == 0.0 and info["loss"] == pytest.approx(info["loss_act"])
    else:
        assert {"loss_future", "loss_future_step0", "loss_future_step1"} <= set(info)
        assert 1e-6 <= info["lambda_z"] <= 0.1 + 1e-7
    if arm == "sigreg":
        assert info["loss"] == pytest.approx(info["loss_act"] + info["lambda_z"] * info["loss_future"]
                                             + 0.09 * info["loss_sigreg"], rel=1e-5)
    if arm == "lambda_a0":
        assert info["loss"] == pytest.approx(info["lambda_z"] * info["loss_future"], rel=1e-5)


def test_compute_loss_is_reproducible_with_a_generator():
    model = tiny_model("jepa").train()
    batch = make_batch(model.cfg)
    l1, _ = model.compute_loss(batch, generator=torch.Generator().manual_seed(7))
    l2, _ = model.compute_loss(batch, generator=torch.Generator().manual_seed(7))
    l3, _ = model.compute_loss(batch, generator=torch.Generator().manual_seed(8))
    assert l1.item() == l2.item() and l1.item() != l3.item()


def test_forward_is_compute_loss_for_ddp():
    model = tiny_model("jepa").train()
    batch = make_batch(model.cfg)
    assert model(batch, torch.Generator().manual_seed(1))[0].item() == \
        model.compute_loss(batch, torch.Generator().manual_seed(1))[0].item()


def test_param_groups_split_every_parameter_once():
    model = tiny_model("dual_cross")
    groups = model.param_groups(weight_decay=0.1)
    ids = [id(p) for g in groups for p in g["params"]]
    assert len(ids) == len(set(ids)) == len(list(model.parameters()))
    no_decay = {id(p) for p in groups[1]["params"]}
    assert id(model.action_pos) in no_decay and id(model.memory.cond_pos) in no_decay
    assert id(model.action_embed.weight) not in no_decay and id(model.action_embed.bias) in no_decay


# ----- MIP is JEPA Policy without the future token -----
def test_mip_equals_jepa_with_the_future_token_removed():
    jepa = tiny_model("jepa", seed=1).eval()
    mip = tiny_model("mip", seed=2).eval()
    missing, unexpected = mip.load_state_dict(jepa.state_dict(), strict=False)
    assert missing == [] and sorted(unexpected) == ["future_embed.bias", "future_embed.weight", "future_head.bias",
                                                    "future_head.weight", "future_pos", "future_type"]
    cfg, b = jepa.cfg, 3
    batch = make_batch(cfg, batch=b)

    def jepa_without_future_token(tokens, a_in, u, v):
        memory = jepa.memory(tokens, u, v)
        return jepa.action_head(jepa.trunk(jepa.action_embed(a_in) + jepa.action_pos, memory))

    t = lambda v: torch.full((b,), v)  # noqa: E731
    images, _, _ = mip._crop_obs(batch["obs"], None, False, None)
    c = mip.encoder(images, mip._lowdim(batch["obs"], b).flatten(0, 1)).view(b, cfg.obs_steps, cfg.width)
    tokens = mip.memory.embed_obs(c)
    a0 = jepa_without_future_token(tokens, torch.zeros(b, cfg.horizon, cfg.action_dim), t(0.0), t(cfg.tau))
    a1 = jepa_without_future_token(tokens, a0, t(cfg.tau), t(1.0))
    actions, z_hat = mip.predict(batch["obs"])
    assert z_hat is None
    assert torch.allclose(actions, mip.normalizer.unnormalize("action", a1), atol=1e-5)
    # the training loss is the action part of the two-step objective with lambda_z = 0
    mip.train()
    loss, info = mip.compute_loss(batch, generator=torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(4)
    mip._crop_obs(batch["obs"], None, True, g)            # the crop draws come first, as in compute_loss
    a = mip.normalizer.normalize("action", batch["action"])
    a_tilde = a + (1 - cfg.tau) * torch.randn(a.shape, generator=g)
    with torch.no_grad():
        images, _, _ = mip._crop_obs(batch["obs"], None, True, torch.Generator().manual_seed(4))
        c = mip.encoder(images, mip._lowdim(batch["obs"], b).flatten(0, 1)).view(b, cfg.obs_steps, cfg.width)
        tokens = mip.memory.embed_obs(c)
        h0 = jepa_without_future_token(tokens, torch.zeros_like(a), t(0.0), t(cfg.tau))
        h1 = jepa_without_future_token(tokens, a_tilde, t(cfg.tau), t(1.0))
    expected, _ = two_step_loss(h0, h1, a, cfg.tau)
    assert loss.item() == pytest.approx(expected.item(), rel=1e-5) and info["lambda_z"] == 0.0


# ----- Diffusion Policy -----
def test_diffusion_runs_the_configured_number_of_denoiser_passes():
    model = tiny_model("diffusion", diffusion_infer_steps=5).eval()
    calls = []
    model.denoiser.register_forward_hook(lambda *_: calls.append(1))
    batch = make_batch(model.cfg, batch=2)
    model.predict(batch["obs"])
    assert len(calls) == 5
    calls.clear()
    model.predict(batch["obs"], num_inference_steps=16)
    assert len(calls) == 16
    with pytest.raises(ValueError, match="num_inference_steps"):
        model.predict(batch["obs"], num_inference_steps=101)
    assert model.scheduler.config.num_train_timesteps == 100
    assert model.scheduler.config.prediction_type == "epsilon"


def test_diffusion_loss_is_epsilon_mse_and_sampling_is_seeded():
    model = tiny_model("diffusion", diffusion_infer_steps=3).eval()
    batch = make_batch(model.cfg, batch=2)
    a1, _ = model.predict(batch["obs"], generator=torch.Generator().manual_seed(0))
    a2, _ = model.predict(batch["obs"], generator=torch.Generator().manual_seed(0))
    assert torch.equal(a1, a2)
    lo, hi = -3.0, 3.0                                      # clip_sample keeps samples inside the data range
    assert a1.min() >= lo - 1e-5 and a1.max() <= hi + 1e-5
    assert isinstance(model, torch.nn.Module) and not isinstance(model, PolicyModel)


def test_two_step_objective_is_learnable_on_a_fixed_batch():
    model = tiny_model("jepa").train()
    batch = make_batch(model.cfg, batch=4)
    optimizer = torch.optim.AdamW(model.param_groups(0.0), lr=3e-3)
    history = []
    for i in range(12):
        loss, info = model.compute_loss(batch, generator=torch.Generator().manual_seed(i))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append(info)
    assert history[-1]["loss"] < 0.5 * history[0]["loss"]
    assert history[-1]["loss_act_step1"] < 0.5 * history[0]["loss_act_step1"]   # the refinement pass learns
    assert history[-1]["loss_future_step1"] < history[0]["loss_future_step1"]
