"""The losses of Sec. 3.3-3.4 and SIGReg (Sec. 4.7) against hand computations of the paper's formulas."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from jepa_policy.losses import adaptive_lambda_z, interval_mse, nmse, sigreg, two_step_loss

TAU = 0.9


def test_nmse_matches_hand_computation():
    z_hat = torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    z = torch.tensor([[1.0, 0.0], [3.0, 4.0]])
    # sample 1: rms^2 = 0.5, ||(0, 2)||^2 / 0.5 / 2 = 4;  sample 2: rms^2 = 12.5, 25 / 12.5 / 2 = 1
    assert nmse(z_hat, z, reduction="none").tolist() == pytest.approx([4.0, 1.0])
    assert nmse(z_hat, z).item() == pytest.approx(2.5)


def test_nmse_floors_the_target_rms():
    z = torch.zeros(1, 2)
    z_hat = torch.tensor([[1e-6, 0.0]])
    # max(rms(z), 1e-6) = 1e-6, so the residual is (1, 0) -> 1 / d_z
    assert nmse(z_hat, z).item() == pytest.approx(0.5, rel=1e-4)


def test_nmse_rejects_mismatched_shapes_and_reductions():
    with pytest.raises(ValueError, match="differs from target"):
        nmse(torch.zeros(2, 3), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="reduction"):
        nmse(torch.zeros(2, 3), torch.ones(2, 3), reduction="sum")


def test_interval_mse_matches_hand_computation():
    a_hat = torch.tensor([[[1.0], [3.0]]])
    a = torch.tensor([[[0.0], [1.0]]])
    assert interval_mse(a_hat, a, 0.5).item() == pytest.approx(((1 / 0.5) ** 2 + (2 / 0.5) ** 2) / 2)


def _two_step_example():
    a = torch.tensor([[[0.0], [1.0]]])
    a0 = torch.tensor([[[0.45], [1.0]]], requires_grad=True)
    a1 = torch.tensor([[[0.0], [1.1]]], requires_grad=True)
    z = torch.tensor([[1.0, 0.0]])
    z0 = torch.tensor([[1.0, 0.9]], requires_grad=True)
    z1 = torch.tensor([[1.0, 0.1]], requires_grad=True)
    return a, a0, a1, z, z0, z1


def test_two_step_loss_adaptive_matches_the_paper_formula():
    a, a0, a1, z, z0, z1 = _two_step_example()
    total, parts = two_step_loss(a0, a1, a, TAU, z_hat0=z0, z_hat1=z1, z=z)
    act0 = (0.45 / TAU) ** 2 / 2                       # <((a_hat0 - a)/tau)^2>, mean over H*A = 2 entries
    act1 = (0.1 / (1 - TAU)) ** 2 / 2
    fut0 = (0.81 / 0.5) / 2 / TAU ** 2                  # NMSE / tau^2 (rms^2 of z = 0.5, d_z = 2)
    fut1 = (0.01 / 0.5) / 2 / (1 - TAU) ** 2
    lam = min(max(0.1 * (act0 + act1) / (fut0 + fut1 + 1e-8), 1e-6), 0.1)
    assert parts["loss_act_step0"].item() == pytest.approx(act0)
    assert parts["loss_act_step1"].item() == pytest.approx(act1)
    assert parts["loss_future_step0"].item() == pytest.approx(fut0)
    assert parts["loss_future_step1"].item() == pytest.approx(fut1)
    assert parts["lambda_z"].item() == pytest.approx(lam)
    assert lam == pytest.approx(0.03125)
    assert total.item() == pytest.approx(act0 + act1 + lam * (fut0 + fut1))


def test_lambda_z_carries_no_gradient():
    a, a0, a1, z, z0, z1 = _two_step_example()
    total, parts = two_step_loss(a0, a1, a, TAU, z_hat0=z0, z_hat1=z1, z=z, lambda_a=2.0)
    total.backward()
    lam = parts["lambda_z"].item()
    assert lam == pytest.approx(min(0.1 * 2.0 * 0.625 / 2.0, 0.1))
    # d/dz0 of lam/tau^2 * ||(z0 - z)/rms||^2 / d_z with lam held constant
    expected_z0 = lam / TAU ** 2 * 2 * (z0.detach() - z) / 0.5 / 2
    assert torch.allclose(z0.grad, expected_z0, atol=1e-6)
    # d/da0 of lambda_a * <((a0 - a)/tau)^2> only: the ratio's sg(L_act) adds nothing
    expected_a0 = 2.0 * 2 * (a0.detach() - a) / TAU ** 2 / 2
    assert torch.allclose(a0.grad, expected_a0, atol=1e-6)


def test_adaptive_lambda_z_is_clipped():
    big, small = torch.tensor(1e3), torch.tensor(1e-3)
    assert adaptive_lambda_z(big, small, 0.1, 1e-6, 0.1).item() == pytest.approx(0.1)
    assert adaptive_lambda_z(small, big, 0.1, 1e-6, 0.1).item() == pytest.approx(1e-6)
    assert adaptive_lambda_z(torch.tensor(2.0), torch.tensor(4.0), 0.1, 1e-6, 0.1).item() == pytest.approx(0.05)


def test_fixed_mode_and_action_only_mip():
    a, a0, a1, z, z0, z1 = _two_step_example()
    total, parts = two_step_loss(a0, a1, a, TAU, z_hat0=z0, z_hat1=z1, z=z, lambda_z_mode="fixed", lambda_z=0.5)
    assert parts["lambda_z"].item() == 0.5
    assert total.item() == pytest.approx(0.625 + 0.5 * (1.0 + 1.0))
    mip_total, mip_parts = two_step_loss(a0, a1, a, TAU)
    assert mip_total.item() == pytest.approx(0.625)
    assert mip_parts["lambda_z"].item() == 0.0 and "loss_future" not in mip_parts


def test_two_step_loss_rejects_partial_future_inputs():
    a, a0, a1, z, z0, _ = _two_step_example()
    with pytest.raises(ValueError, match="together"):
        two_step_loss(a0, a1, a, TAU, z_hat0=z0, z=z)
    with pytest.raises(ValueError, match="lambda_z_mode"):
        two_step_loss(a0, a1, a, TAU, z_hat0=z0, z_hat1=z0, z=z, lambda_z_mode="auto")


def _sigreg_reference(x: np.ndarray, directions: np.ndarray, num_points=17, t_max=5.0) -> float:
    """Epps-Pulley statistic with complex arithmetic, averaged over unit directions."""
    directions = directions / np.linalg.norm(directions, axis=0, keepdims=True)
    t = np.linspace(-t_max, t_max, num_points)
    phi = np.exp(-0.5 * t ** 2)
    stats = []
    for s in range(directions.shape[1]):
        p = x @ directions[:, s]
        ecf = np.exp(1j * np.outer(p, t)).mean(axis=0)
        stats.append(np.trapezoid(np.abs(ecf - phi) ** 2 * phi, t) * x.shape[0])
    return float(np.mean(stats))


def test_sigreg_matches_reference_and_separates_gaussian_from_collapse():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2048, 8, generator=g, dtype=torch.float64)
    stat = sigreg(x, num_slices=32, generator=torch.Generator().manual_seed(5))
    directions = torch.randn(8, 32, generator=torch.Generator().manual_seed(5), dtype=torch.float32).double()
    assert stat.item() == pytest.approx(_sigreg_reference(x.numpy(), directions.numpy()), rel=1e-6)
    collapsed = sigreg(torch.zeros(2048, 8, dtype=torch.float64) + 0.5, num_slices=32,
                       generator=torch.Generator().manual_seed(5))
    squashed = sigreg(0.1 * x, num_slices=32, generator=torch.Generator().manual_seed(5))
    assert stat.item() < 5.0          # N(0, I): the statistic stays O(1) (about 1 in expectation)
    assert collapsed.item() > 100 * stat.item() and squashed.item() > 100 * stat.item()


def test_sigreg_gradient_pushes_toward_isotropy():
    x = (0.1 * torch.randn(512, 4, generator=torch.Generator().manual_seed(1))).requires_grad_()
    stat = sigreg(x, num_slices=16, generator=torch.Generator().manual_seed(2))
    stat.backward()
    # Shrunken latents: descending the statistic must spread them out (x . grad < 0).
    assert (x.detach() * x.grad).sum().item() < 0
    with pytest.raises(ValueError, match="shape"):
        sigreg(torch.zeros(1, 4))
    assert math.isfinite(stat.item())
