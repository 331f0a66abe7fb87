"""The checkpoint file that ``jepa-policy train`` writes, and reading it back safely.

A checkpoint holds everything a run needs to continue bit-exactly (weights, EMA, optimiser, schedule, RNG,
sampler position) and everything ``Policy.from_checkpoint`` needs to act (model config, task, image size,
normaliser statistics, the dataset's env_args). ``train.py`` writes it; ``policy.py``, the evaluation and the
audits read it through ``load_checkpoint`` / ``load_model``.
"""
from __future__ import annotations

import hashlib
import os
import pickle
import random
import re
from pathlib import Path

import numpy as np
import torch

from jepa_envs.errors import first_line
from jepa_policy.blocks import BasePolicyModel
from jepa_policy.config import ModelConfig
from jepa_policy.lerobot_format import read_lerobot_checkpoint
from jepa_policy.model import build_model

FORMAT = "jepa-policy-checkpoint/1"
EMA_PREFIX = "module."   # torch's AveragedModel keeps the averaged network under .module


class UnsafeCheckpoint(ValueError):
    """A file that is not plain data: loading it could run code, so it is refused unread."""


# What a checkpoint may hold besides tensors, numbers, strings and containers: numeric numpy arrays (normaliser
# statistics, NumPy's generator state). The restricted unpickler builds nothing else, so a file whose pickle
# calls a function (os.system ...) or builds any other object (an object array included) is refused.
_NUMERIC_DTYPES = ("Bool", "Int8", "Int16", "Int32", "Int64", "UInt8", "UInt16", "UInt32", "UInt64", "Float16",
                   "Float32", "Float64")
SAFE_GLOBALS = [np.ndarray, np.dtype, (np._core.multiarray._reconstruct, "numpy._core.multiarray._reconstruct"),
                (np._core.multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),   # numpy 1.x pickles
                *(getattr(np.dtypes, f"{name}DType") for name in _NUMERIC_DTYPES)]


def safe_load(path: Path, map_location="cpu", what: str = "checkpoint"):
    """``torch.load`` that reads data only (``weights_only`` with the numeric-array allowlist above).

    A file that needs anything else raises UnsafeCheckpoint; a truncated or foreign file ValueError; both name
    the file and what to do.
    """
    try:
        with torch.serialization.safe_globals(SAFE_GLOBALS):
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        detail = str(exc)
        found = re.search(r"(unsupported (?:global: )?GLOBAL [\w.]+|got <class '[\w.]+'>|unsupported operand \d+)",
                          detail, re.IGNORECASE)
        if "weights_only" not in detail and "WeightsUnpickler" not in detail and found is None:
            raise ValueError(f"{path} is not a readable {what} ({_first_line(detail)}); pass a .pt file written by "
                             "`jepa-policy train` (or a torch state_dict for encoder weights)") from None
        raise UnsafeCheckpoint(
            f"refused {path}: it holds more than tensors and numeric arrays ({found.group(0) if found else 'code'}), "
            f"so loading it could run code; it was not loaded. Use a {what} written by `jepa-policy train`, or a "
            "plain state_dict of tensors") from None
    except Exception as exc:   # torch raises RuntimeError, KeyError, EOFError ... for bytes that are not a .pt
        raise ValueError(f"{path} is not a readable {what} (truncated, or not a torch file: "
                         f"{_first_line(str(exc))}); pass a .pt file written by `jepa-policy train`") from None


def _first_line(text: str) -> str:
    """The first sentence of an error text, bounded (torch's messages run on for paragraphs)."""
    return first_line(text).split(". ")[0]


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


def save_eval_snapshot(path: Path, *, ema, step: int, cfg, model_cfg: ModelConfig, spec,
                       env_args: dict | None = None) -> None:
    """The EMA weights of one periodic evaluation: enough to act (``Policy.from_checkpoint``), not to resume."""
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": FORMAT, "step": step, "train_config": cfg.to_dict(), "model_config": model_cfg.to_dict(),
               "task": spec.name, "image_size": spec.image_size, "env_args": env_args, "ema": ema.state_dict(),
               "eval_snapshot": True}
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """The checkpoint's payload; a clear error for a missing file or a file of another kind. A directory is read
    as a checkpoint of the LeRobot ``jepa`` policy (``jepa_policy.lerobot_format``)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist; pass the .pt file written by `jepa-policy train`")
    if path.is_dir():
        # a LeRobot ``jepa`` policy's pretrained_model folder: no EMA there, its weights are the ones to act with
        payload = read_lerobot_checkpoint(path)
        payload["ema"] = {EMA_PREFIX + key: value for key, value in payload["model"].items()}
        return {"format": FORMAT, **payload}
    payload = safe_load(path, map_location)
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


BACKBONE = "encoder.cameras."   # the per-camera ResNet-18 GN backbones: what a pretrained encoder replaces


def load_encoder_weights(model: BasePolicyModel, path: str | Path,
                         key_map: tuple[tuple[str, str], ...] = ()) -> tuple[int, str]:
    """Initialise the image backbones (``encoder.cameras.*``) from a local file; returns (tensors, sha256).

    The file is a ``jepa-policy train`` checkpoint (its EMA weights are used), or any state_dict (optionally
    under "state_dict"). ``key_map`` pairs (source prefix, our prefix) rename its keys, e.g.
    ``[["", "encoder.cameras.agentview_image."]]`` for a bare ResNet18GN state_dict of one camera, or
    ``[["backbone.", "encoder.cameras.agentview_image."]]``; without a map the keys must already be ours.
    Every backbone tensor must be provided with its exact shape; anything else is an error naming the keys.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"encoder weights {path} do not exist; pass a local file (no download is made)")
    raw = path.read_bytes()
    state = safe_load(path, "cpu", what="encoder weights file")
    if isinstance(state, dict) and state.get("format") == FORMAT:
        state = {k[len(EMA_PREFIX):]: v for k, v in state["ema"].items() if k.startswith(EMA_PREFIX)}
    elif isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{path} holds no state_dict (a mapping of names to tensors)")
    pairs = key_map or ((BACKBONE, BACKBONE),)
    mapped = {}
    for key, value in state.items():
        for src, dst in pairs:
            if key.startswith(src) and (dst + key[len(src):]).startswith(BACKBONE):
                mapped[dst + key[len(src):]] = value
                break
    own = {k: v for k, v in model.state_dict().items() if k.startswith(BACKBONE)}
    missing = sorted(set(own) - set(mapped))
    unexpected = sorted(set(mapped) - set(own))
    wrong = sorted(k for k in set(own) & set(mapped) if tuple(own[k].shape) != tuple(mapped[k].shape))
    if missing or unexpected or wrong:
        raise ValueError(f"{path} does not fit this model's image backbone: {len(missing)} missing (e.g. "
                         f"{missing[:3]}), {len(unexpected)} unexpected (e.g. {unexpected[:3]}), {len(wrong)} of "
                         f"another shape (e.g. {wrong[:3]}); check cameras, encoder_width and encoder_key_map")
    model.load_state_dict(mapped, strict=False)
    return len(mapped), hashlib.sha256(raw).hexdigest()


def freeze_backbone(model: BasePolicyModel) -> int:
    """Stop training the image backbones; returns how many tensors were frozen (fusion and heads still learn)."""
    frozen = 0
    for name, p in model.named_parameters():
        if name.startswith(BACKBONE):
            p.requires_grad_(False)
            frozen += 1
    return frozen
