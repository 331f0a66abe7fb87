"""Tiny model configurations and synthetic batches for the model tests (CPU, milliseconds per step)."""
from __future__ import annotations

import numpy as np
import torch

from jepa_policy.config import ModelConfig
from jepa_policy.model import build_model

TINY = dict(image_size=24, encoder_width=8, width=32, layers=2, heads=2, time_emb_dim=8, dropout=0.0,
            dual_future_width=16, dual_future_layers=2, diffusion_keypoints=4, diffusion_feature_dim=8,
            sigreg_slices=16)


def tiny_config(arm: str = "jepa", task: str = "ToolHang", **overrides) -> ModelConfig:
    return ModelConfig.for_task(task, arm=arm, **{**TINY, **overrides})


def unit_stats(cfg: ModelConfig, half_range: float = 3.0) -> dict:
    stats = {"action": {"min": -half_range * np.ones(cfg.action_dim), "max": half_range * np.ones(cfg.action_dim)}}
    for key, dim in cfg.lowdim:
        stats[key] = {"min": -half_range * np.ones(dim), "max": half_range * np.ones(dim)}
    return stats


def tiny_model(arm: str = "jepa", seed: int = 0, **overrides):
    torch.manual_seed(seed)
    cfg = tiny_config(arm, **overrides)
    model = build_model(cfg)
    model.set_normalizer_stats(unit_stats(cfg))
    return model


def make_batch(cfg: ModelConfig, batch: int = 3, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    s = cfg.image_size
    obs = {k: torch.randint(0, 256, (batch, cfg.obs_steps, s, s, 3), generator=g, dtype=torch.uint8)
           for k in cfg.image_keys}
    for key, dim in cfg.lowdim:
        obs[key] = torch.randn(batch, cfg.obs_steps, dim, generator=g)
    future = {k: torch.randint(0, 256, (batch, s, s, 3), generator=g, dtype=torch.uint8) for k in cfg.image_keys}
    action = 2.0 * torch.rand(batch, cfg.horizon, cfg.action_dim, generator=g) - 1.0
    return {"obs": obs, "future_obs": future, "action": action}
