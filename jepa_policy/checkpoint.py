"""Building a model from its config, and the checkpoint file that ``jepa-policy train`` writes.

A checkpoint holds everything a run needs to continue bit-exactly (weights, EMA, optimiser, schedule, RNG,
sampler position) and everything ``Policy.from_checkpoint`` needs to act (model config, task, image size,
normaliser statistics, the dataset's env_args). ``train.py`` writes it; ``policy.py``, the evaluation and the
audits read it through ``load_checkpoint`` / ``load_model``.
"""
from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

from jepa_policy.blocks import BasePolicyModel
from jepa_policy.config import ModelConfig
from jepa_policy.diffusion import DiffusionPolicyModel
from jepa_policy.model import PolicyModel

FORMAT = "jepa-policy-checkpoint/1"
EMA_PREFIX = "module."   # torch's AveragedModel keeps the averaged network under .module


def build_model(cfg: ModelConfig) -> BasePolicyModel:
    """The model of ``cfg.arm``: PolicyModel for the two-step arms, DiffusionPolicyModel for ``diffusion``."""
    if cfg.arm == "diffusion":
        return DiffusionPolicyModel(cfg)
    return PolicyModel(cfg)


def rng_state() -> dict:
    """Python, NumPy, torch (and CUDA) generator states, so a resumed run draws what the uninterrupted one did."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, *, model, ema, optimizer, scheduler, step: int, cfg, model_cfg: ModelConfig,
                    spec, stats: dict, curve: list, sampler_position: dict, env_args: dict | None = None,
                    init_selection: dict | None = None) -> None:
    """Write atomically (temporary file, then rename); ``cfg`` is the run's ``TrainConfig``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "step": step,
        "train_config": cfg.to_dict(),
        "model_config": model_cfg.to_dict(),
        "task": spec.name,
        "image_size": spec.image_size,
        "normalizer_stats": stats,
        "env_args": env_args,
        "model": model.state_dict(),
        "ema": ema.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "rng": rng_state(),
        "sampler": sampler_position,
        "eval_curve": curve,
        "init_selection": init_selection,
    }
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """The checkpoint's payload; a clear error for a missing file or a file of another kind."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist; pass the .pt file written by `jepa-policy train`")
    payload = torch.load(path, map_location=map_location, weights_only=False)
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path} is not a jepa-policy checkpoint (missing format tag)")
    return payload


def load_model(ckpt: dict, ema: bool = True) -> BasePolicyModel:
    """The network of a loaded checkpoint with its EMA weights (``ema=False``: the raw training weights)."""
    model = build_model(ModelConfig.from_dict(ckpt["model_config"]))
    if ema:
        state = {k[len(EMA_PREFIX):]: v for k, v in ckpt["ema"].items() if k.startswith(EMA_PREFIX)}
    else:
        state = ckpt["model"]
    model.load_state_dict(state)
    return model
