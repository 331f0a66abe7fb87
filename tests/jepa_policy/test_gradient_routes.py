"""Where the future objective can reach (Sec. 3.3, 4.5): stop-gradient target, back-cut, fwd-cut, dual stacks."""
from __future__ import annotations

import pytest
import torch
from _model_helpers import make_batch, tiny_model

# lambda_a = 0 with a fixed lambda_z leaves only the future loss: its gradient is what each test inspects.
FUTURE_ONLY = dict(lambda_a=0.0, lambda_z_mode="fixed", lambda_z=1.0)


def future_loss_grads(arm: str, **overrides) -> dict[str, torch.Tensor]:
    model = tiny_model(arm, **{**FUTURE_ONLY, **overrides}).train()
    loss, _ = model.compute_loss(make_batch(model.cfg), generator=torch.Generator().manual_seed(0))
    loss.backward()
    return {n: (torch.zeros_like(p) if p.grad is None else p.grad) for n, p in model.named_parameters()}


def total_norm(grads: dict, prefixes: tuple[str, ...]) -> float:
    return sum(g.abs().sum().item() for n, g in grads.items() if n.split(".", 1)[0] in prefixes)


def test_future_target_is_computed_without_gradient():
    model = tiny_model("jepa").train()
    outputs = []
    for net in model.encoder.cameras.values():
        net.register_forward_hook(lambda _m, _i, out: outputs.append(out.requires_grad))
    model.compute_loss(make_batch(model.cfg), generator=torch.Generator().manual_seed(0))
    n = len(model.cfg.cameras)
    assert outputs == [True] * n + [False] * n        # o_t path carries gradient, sg(E_rgb(o_{t+k})) does not


def test_future_loss_reaches_the_encoder_through_the_current_observation():
    grads = future_loss_grads("jepa")
    assert total_norm(grads, ("encoder",)) > 0
    assert total_norm(grads, ("trunk", "memory")) > 0
    assert total_norm(grads, ("action_head",)) == 0     # lambda_a = 0 really removed the action loss


def test_backcut_future_loss_puts_zero_gradient_on_the_shared_trunk():
    grads = future_loss_grads("backcut")
    trunk = ("encoder", "memory", "trunk", "action_embed", "action_pos", "future_embed", "future_type",
             "future_pos")
    assert total_norm(grads, trunk) == 0.0
    assert total_norm(grads, ("future_head",)) > 0
    assert total_norm(future_loss_grads("jepa"), ("trunk",)) > 0        # the same check fails on JEPA Policy


def test_fwdcut_action_outputs_do_not_depend_on_the_future_token():
    for arm, independent in (("fwdcut", True), ("jepa", False)):
        model = tiny_model(arm).eval()
        cfg, b = model.cfg, 2
        tokens = torch.randn(b, cfg.obs_steps, cfg.width)
        a_in = torch.randn(b, cfg.horizon, cfg.action_dim)
        u, v = torch.full((b,), cfg.tau), torch.ones(b)
        a1, z1 = model.step(tokens, a_in, torch.randn(b, cfg.future_dim), u, v)
        a2, z2 = model.step(tokens, a_in, 10 * torch.randn(b, cfg.future_dim), u, v)
        assert torch.equal(a1, a2) is independent, arm
        assert not torch.allclose(z1, z2)                               # the future token still sees the actions


def test_fwdcut_future_loss_still_shapes_the_trunk():
    grads = future_loss_grads("fwdcut")
    assert total_norm(grads, ("trunk",)) > 0 and total_norm(grads, ("encoder",)) > 0


def test_dual_independent_future_loss_puts_zero_gradient_on_the_action_stack():
    grads = future_loss_grads("dual_independent")
    assert total_norm(grads, ("action_stack", "action_embed", "action_pos", "action_head")) == 0.0
    assert total_norm(grads, ("future_stack",)) > 0
    assert total_norm(grads, ("memory", "encoder")) > 0               # the shared conditioning path still learns
    assert total_norm(future_loss_grads("dual_cross"), ("action_stack",)) > 0   # the cross block links them


def test_gradient_share_on_the_action_readout():
    shares = {}
    for arm in ("jepa", "backcut", "dual_independent", "dual_cross", "mip"):
        model = tiny_model(arm).train()
        shares[arm] = model.gradient_share(make_batch(model.cfg), generator=torch.Generator().manual_seed(0))
    assert shares["dual_independent"] == 0.0 and shares["backcut"] == 0.0 and shares["mip"] == 0.0
    assert shares["jepa"] > 0 and shares["dual_cross"] > 0


def test_loss_terms_sum_to_the_loss():
    model = tiny_model("sigreg").train()
    batch = make_batch(model.cfg)
    terms, parts = model.loss_terms(batch, generator=torch.Generator().manual_seed(2))
    loss, info = model.compute_loss(batch, generator=torch.Generator().manual_seed(2))
    assert set(terms) == {"act", "future", "sigreg"}
    assert info["loss"] == loss.item()
    assert sum(t.item() for t in terms.values()) == pytest.approx(loss.item(), rel=1e-6)
    assert terms["future"].item() == pytest.approx(info["lambda_z"] * info["loss_future"], rel=1e-6)
