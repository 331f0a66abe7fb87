"""JEPA Policy's losses as pure functions of tensors (Sec. 3.3-3.4, 4.7), testable against hand computation."""
from __future__ import annotations

import torch
from torch import Tensor

from monitor_service.scoring import RMS_FLOOR

RATIO_EPS = 1e-8     # epsilon of the adaptive ratio (Sec. 3.3)


def nmse(z_hat: Tensor, z: Tensor, reduction: str = "mean") -> Tensor:
    """Target-RMS-normalised MSE (Sec. 3.3).

    d_NMSE(z_hat, z) = || (z_hat - z) / max(||z||_RMS, 1e-6) ||^2 / d_z per sample; averaged over the batch
    when ``reduction="mean"``, one value per sample with ``"none"``. The caller applies stop-gradient to the
    target; this function does not. It is ``monitor_service.scoring.nmse_rows`` (the project's one d_NMSE, which
    scores rollouts, the monitor and the server) in torch, so that it carries gradients on the training device;
    tests/jepa_policy/test_nmse_agreement.py holds the two together on random inputs.
    """
    if z_hat.shape != z.shape:
        raise ValueError(f"nmse: prediction shape {tuple(z_hat.shape)} differs from target {tuple(z.shape)}")
    rms = z.pow(2).mean(dim=-1, keepdim=True).sqrt().clamp_min(RMS_FLOOR)
    per_sample = ((z_hat - z) / rms).pow(2).mean(dim=-1)
    if reduction == "none":
        return per_sample
    if reduction == "mean":
        return per_sample.mean()
    raise ValueError(f"nmse: reduction={reduction!r}; use 'mean' or 'none'")


def interval_mse(a_hat: Tensor, a: Tensor, interval: float) -> Tensor:
    """<((a_hat - a) / interval)^2>: mean over action dims, horizon and batch (Sec. 3.3-3.4)."""
    if a_hat.shape != a.shape:
        raise ValueError(f"interval_mse: prediction shape {tuple(a_hat.shape)} differs from target {tuple(a.shape)}")
    return ((a_hat - a) / interval).pow(2).mean()


def adaptive_lambda_z(weighted_act: Tensor, future: Tensor, rho: float, lo: float, hi: float) -> Tensor:
    """Eq. (ratio_mode): lambda_z = clip(rho * sg(lambda_a L_act) / (sg(L_future) + 1e-8), lo, hi).

    Carries no gradient: stop-gradient applies inside the ratio only.
    """
    return (rho * weighted_act.detach() / (future.detach() + RATIO_EPS)).clamp(lo, hi)


def two_step_terms(
    a_hat0: Tensor, a_hat1: Tensor, a: Tensor, tau: float, *,
    z_hat0: Tensor | None = None, z_hat1: Tensor | None = None, z: Tensor | None = None,
    lambda_a: float = 1.0, lambda_z_mode: str = "adaptive", lambda_z: float = 0.01,
    rho: float = 0.10, lambda_z_min: float = 1e-6, lambda_z_max: float = 0.1,
) -> tuple[Tensor, Tensor | None, dict[str, Tensor]]:
    """The two weighted terms of the two-step objective, lambda_a L_act and lambda_z L_future (None without
    future predictions), and their detached parts. ``two_step_loss`` documents the formulas."""
    act0 = interval_mse(a_hat0, a, tau)
    act1 = interval_mse(a_hat1, a, 1.0 - tau)
    loss_act = act0 + act1
    parts: dict[str, Tensor] = {"loss_act_step0": act0.detach(), "loss_act_step1": act1.detach(),
                                "loss_act": loss_act.detach()}
    act_term = lambda_a * loss_act
    if z_hat0 is None and z_hat1 is None:
        parts["lambda_z"] = torch.zeros((), dtype=loss_act.dtype, device=loss_act.device)
        return act_term, None, parts
    if z_hat0 is None or z_hat1 is None or z is None:
        raise ValueError("two_step_loss: give z_hat0, z_hat1 and z together (or none for action-only MIP)")
    fut0 = nmse(z_hat0, z) / tau ** 2
    fut1 = nmse(z_hat1, z) / (1.0 - tau) ** 2
    loss_future = fut0 + fut1
    if lambda_z_mode == "adaptive":
        lz = adaptive_lambda_z(act_term, loss_future, rho, lambda_z_min, lambda_z_max)
    elif lambda_z_mode == "fixed":
        lz = torch.as_tensor(float(lambda_z), dtype=loss_future.dtype, device=loss_future.device)
    else:
        raise ValueError(f"two_step_loss: lambda_z_mode={lambda_z_mode!r}; use 'adaptive' or 'fixed'")
    parts.update(loss_future_step0=fut0.detach(), loss_future_step1=fut1.detach(),
                 loss_future=loss_future.detach(), lambda_z=lz.detach())
    return act_term, lz * loss_future, parts


def two_step_loss(a_hat0: Tensor, a_hat1: Tensor, a: Tensor, tau: float,
                  **kwargs) -> tuple[Tensor, dict[str, Tensor]]:
    """The MIP-style two-step objective with the paired future term (Sec. 3.4, Eq. mip_loss).

    Step 1 (inputs zero, (u,v)=(0,tau)): lambda_a <((a_hat0 - a)/tau)^2> + lambda_z/tau^2 NMSE(z_hat0, z).
    Step 2 (noised targets, (u,v)=(tau,1)): the same with 1 - tau. L = L^(0) + L^(1).
    In adaptive mode one lambda_z, shared by both steps, comes from the sums of the unweighted,
    interval-scaled components of both steps. ``z`` must already be stop-gradiented by the caller.
    Without future predictions (MIP) the future term is absent (lambda_z = 0).
    Keyword arguments: z_hat0, z_hat1, z, lambda_a, lambda_z_mode, lambda_z, rho, lambda_z_min, lambda_z_max.
    Returns the total loss and its detached parts.
    """
    act_term, future_term, parts = two_step_terms(a_hat0, a_hat1, a, tau, **kwargs)
    return (act_term if future_term is None else act_term + future_term), parts


def sigreg(x: Tensor, num_slices: int = 256, num_points: int = 17, t_max: float = 5.0,
           generator: torch.Generator | None = None) -> Tensor:
    """SIGReg (LeJEPA-style, Sec. 4.7): Epps-Pulley test of 1-D random projections against N(0, 1).

    x: (N, D) latents. For each unit direction a, with p = x a, the statistic is
    N * integral over t of |mean_n exp(i t p_n) - exp(-t^2/2)|^2 exp(-t^2/2) dt (trapezoid on [-t_max, t_max]),
    averaged over ``num_slices`` directions. It is zero in expectation only for isotropic N(0, I) latents.
    """
    if x.dim() != 2 or x.shape[0] < 2:
        raise ValueError(f"sigreg: expected latents of shape (N>=2, D), got {tuple(x.shape)}")
    gen_device = generator.device if generator is not None else x.device
    a = torch.randn(x.shape[1], num_slices, generator=generator, device=gen_device).to(x.device, x.dtype)
    a = a / a.norm(dim=0, keepdim=True)
    t = torch.linspace(-t_max, t_max, num_points, device=x.device, dtype=x.dtype)
    target = torch.exp(-0.5 * t ** 2)
    xt = (x @ a).unsqueeze(-1) * t                       # (N, slices, points)
    err = (xt.cos().mean(0) - target).pow(2) + xt.sin().mean(0).pow(2)
    stat = torch.trapezoid(err * target, t, dim=-1) * x.shape[0]
    return stat.mean()

