"""Network pieces and observation handling that every arm shares: the JEPA family (``model.py``) and the
Diffusion Policy arm (``diffusion.py``) both build on this file.

ResNet-18 with GroupNorm (the image encoder of Sec. 3.2, 4.1), sinusoidal features, the pre-norm Transformer
layer (self-attention, cross-attention to a memory, FFN), the temporal-consistent crop (Sec. 4.1), the
``BasePolicyModel`` with normalisers, checks and AdamW groups, and the two weight initialisations.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from jepa_policy.config import ModelConfig
from jepa_policy.normalizer import ImageStandardizer, Normalizer

# ----------------------------------------------------------------------------------------------------------
# Image encoder: ResNet-18 with GroupNorm, from scratch (Sec. 3.2, 4.1)
# ----------------------------------------------------------------------------------------------------------


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with 16 channels per group, the Diffusion Policy / MIP replacement for BatchNorm."""
    return nn.GroupNorm(max(1, channels // 16), channels)


class BasicBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.norm1 = group_norm(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.norm2 = group_norm(c_out)
        self.downsample = None
        if stride != 1 or c_in != c_out:
            self.downsample = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), group_norm(c_out))

    def forward(self, x: Tensor) -> Tensor:
        out = F.relu(self.norm1(self.conv1(x)))
        out = self.norm2(self.conv2(out))
        skip = x if self.downsample is None else self.downsample(x)
        return F.relu(out + skip)


class ResNet18GN(nn.Module):
    """ResNet-18 (He et al.) with GroupNorm; ``width`` 64 is the real network (11.18 M parameters)."""

    def __init__(self, width: int = 64):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, width, 7, 2, 3, bias=False), group_norm(width), nn.ReLU(),
                                  nn.MaxPool2d(3, 2, 1))
        widths = [width, 2 * width, 4 * width, 8 * width]
        stages, c_in = [], width
        for i, w in enumerate(widths):
            stride = 1 if i == 0 else 2
            stages.append(nn.Sequential(BasicBlock(c_in, w, stride), BasicBlock(w, w, 1)))
            c_in = w
        self.stages = nn.Sequential(*stages)
        self.out_dim = widths[-1]

    def feature_map(self, x: Tensor) -> Tensor:
        return self.stages(self.stem(x))

    def forward(self, x: Tensor) -> Tensor:
        """(N, 3, h, w) float -> (N, 8 * width) by global average pooling."""
        return self.feature_map(x).mean(dim=(-2, -1))


# ----------------------------------------------------------------------------------------------------------
# Sinusoidal features of a scalar (time embeddings)
# ----------------------------------------------------------------------------------------------------------


def sinusoid(x: Tensor, dim: int) -> Tensor:
    """Transformer sinusoidal features of a scalar per sample: (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=x.device, dtype=torch.float32) / half)
    angles = x.float()[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


# ----------------------------------------------------------------------------------------------------------
# Transformer layer
# ----------------------------------------------------------------------------------------------------------


class Attention(nn.Module):
    """Multi-head attention; ``kv_dim`` lets one branch read another of a different width."""

    def __init__(self, dim: int, heads: int, kv_dim: int | None = None, dropout: float = 0.0):
        super().__init__()
        kv_dim = dim if kv_dim is None else kv_dim
        self.heads, self.dropout = heads, dropout
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(kv_dim, dim)
        self.v = nn.Linear(kv_dim, dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, context: Tensor, mask: Tensor | None = None) -> Tensor:
        b, tq, d = x.shape
        tk, h = context.shape[1], self.heads
        q = self.q(x).view(b, tq, h, d // h).transpose(1, 2)
        k = self.k(context).view(b, tk, h, d // h).transpose(1, 2)
        v = self.v(context).view(b, tk, h, d // h).transpose(1, 2)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask,
                                           dropout_p=self.dropout if self.training else 0.0)
        return self.proj(y.transpose(1, 2).reshape(b, tq, d))


class FeedForward(nn.Module):
    def __init__(self, dim: int, mult: int):
        super().__init__()
        self.fc = nn.Linear(dim, mult * dim)
        self.proj = nn.Linear(mult * dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(F.gelu(self.fc(x)))


class SharedBlock(nn.Module):
    """One pre-norm layer: self-attention over the tokens, cross-attention to M, FFN (Sec. 3.2).

    The three sub-steps are separate methods because the dual-cross arm puts its cross block between
    self-attention and memory attention (Sec. 4.2).
    """

    def __init__(self, dim: int, heads: int, ffn_mult: int, dropout: float):
        super().__init__()
        self.norm_self = nn.LayerNorm(dim)
        self.self_attn = Attention(dim, heads, dropout=dropout)
        self.norm_mem = nn.LayerNorm(dim)
        self.mem_attn = Attention(dim, heads, dropout=dropout)
        self.norm_ffn = nn.LayerNorm(dim)
        self.ffn = FeedForward(dim, ffn_mult)
        self.drop = nn.Dropout(dropout)

    def self_attend(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        h = self.norm_self(x)
        return x + self.drop(self.self_attn(h, h, mask))

    def read_memory(self, x: Tensor, memory: Tensor, mask: Tensor | None = None) -> Tensor:
        return x + self.drop(self.mem_attn(self.norm_mem(x), memory, mask))

    def feed_forward(self, x: Tensor) -> Tensor:
        return x + self.drop(self.ffn(self.norm_ffn(x)))

    def forward(self, x: Tensor, memory: Tensor, self_mask: Tensor | None = None,
                memory_mask: Tensor | None = None) -> Tensor:
        return self.feed_forward(self.read_memory(self.self_attend(x, self_mask), memory, memory_mask))

# ----------------------------------------------------------------------------------------------------------
# Observation handling shared by every arm (normalisation, temporal-consistent crop, validation)
# ----------------------------------------------------------------------------------------------------------


def crop_windows(n: int, size: int, crop: int, random: bool, generator: torch.Generator | None,
                 device: torch.device) -> tuple[Tensor, Tensor]:
    """Top-left corners (n,) of crop windows: uniform when ``random``, the centre otherwise."""
    if not random or crop == size:
        off = torch.full((n,), (size - crop) // 2, dtype=torch.long)
        return off.to(device), off.to(device)
    gen_device = generator.device if generator is not None else torch.device("cpu")
    top = torch.randint(0, size - crop + 1, (n,), generator=generator, device=gen_device)
    left = torch.randint(0, size - crop + 1, (n,), generator=generator, device=gen_device)
    return top.to(device), left.to(device)


def crop_frames(frames: Tensor, top: Tensor, left: Tensor, crop: int) -> Tensor:
    """(B, T, H, W, C) with one window per batch element, shared by its T frames -> (B, T, crop, crop, C)."""
    if crop == frames.shape[2] == frames.shape[3]:
        return frames  # no crop (crop_ratio 1.0): the gather below would only copy, at ~7 % of a CPU step
    ar = torch.arange(crop, device=frames.device)
    rows = (top[:, None] + ar)[:, None, :, None]          # (B, 1, crop, 1)
    cols = (left[:, None] + ar)[:, None, None, :]         # (B, 1, 1, crop)
    b = torch.arange(frames.shape[0], device=frames.device)[:, None, None, None]
    t = torch.arange(frames.shape[1], device=frames.device)[None, :, None, None]
    return frames[b, t, rows, cols]


def to_chw_float(x: Tensor) -> Tensor:
    """uint8 (..., h, w, 3) -> float (..., 3, h, w) in [0, 1]."""
    return x.movedim(-1, -3).float().div_(255.0)


class BasePolicyModel(nn.Module):
    """What every arm shares: the normaliser, observation checks and crops, AdamW parameter groups.

    ``forward(batch)`` is ``compute_loss(batch)`` so DistributedDataParallel can wrap the model.
    """

    cfg: ModelConfig

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.normalizer = Normalizer({"action": cfg.action_dim, **dict(cfg.lowdim)})
        # Only models that standardise pixels own the module, so "unit" checkpoints keep their state_dict.
        self.image_normalizer = ImageStandardizer(cfg.image_keys) if cfg.image_norm == "dataset" else None

    # ----- public API -----
    def set_normalizer_stats(self, stats: Mapping[str, Mapping[str, np.ndarray]]) -> None:
        """stats = {"action": {"min", "max"}, "<lowdim key>": {...}} (numpy arrays), plus
        {"<image key>": {"mean", "std"}} when ``image_norm == "dataset"`` (``dataset.normalizer_stats``)."""
        self.normalizer.set_stats(stats)
        if self.image_normalizer is not None:
            self.image_normalizer.set_stats(stats)

    def forward(self, batch: Mapping, generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        return self.compute_loss(batch, generator)

    def param_groups(self, weight_decay: float) -> list[dict]:
        """AdamW groups: matrices and conv kernels decay; biases, norms and learned positions do not."""
        decay, no_decay = [], []
        for name, p in self.named_parameters():
            if not p.requires_grad:
                continue
            is_position = name.rsplit(".", 1)[-1] in ("action_pos", "future_pos", "future_type", "cond_pos",
                                                        "pos_emb", "cond_pos_emb")
            (decay if p.dim() >= 2 and not is_position else no_decay).append(p)
        return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # ----- observation helpers -----
    def _as_tensor(self, x, name: str) -> Tensor:
        if isinstance(x, np.ndarray):
            x = torch.from_numpy(np.ascontiguousarray(x))
        if not torch.is_tensor(x):
            raise TypeError(f"{name}: expected a torch tensor or numpy array, got {type(x).__name__}")
        return x.to(self.device, non_blocking=True)

    def _images(self, source: Mapping, key: str, where: str, with_time: bool) -> Tensor:
        if key not in source:
            raise KeyError(f"{where} lacks image key {key!r}; the model was configured with cameras "
                           f"{self.cfg.cameras} (keys {self.cfg.image_keys})")
        x = self._as_tensor(source[key], f"{where}[{key!r}]")
        s = self.cfg.image_size
        want = ("B", self.cfg.obs_steps, s, s, 3) if with_time else ("B", s, s, 3)
        if x.dtype != torch.uint8 or x.dim() != len(want) or tuple(x.shape[1:]) != want[1:]:
            raise ValueError(f"{where}[{key!r}] must be uint8 of shape {want}; got {x.dtype} {tuple(x.shape)} "
                             "(images are HWC uint8 as the envs emit them; resize to the config's image_size)")
        return x

    def _lowdim(self, obs: Mapping, batch_size: int) -> Tensor:
        """Normalised low-dim inputs, concatenated in config order: (B, T_obs, D)."""
        parts = []
        for key, dim in self.cfg.lowdim:
            if key not in obs:
                raise KeyError(f"obs lacks low-dim key {key!r}; the model expects {list(self.cfg.lowdim_keys)}")
            x = self._as_tensor(obs[key], f"obs[{key!r}]").float()
            if tuple(x.shape) != (batch_size, self.cfg.obs_steps, dim):
                raise ValueError(f"obs[{key!r}] must have shape (B={batch_size}, {self.cfg.obs_steps}, {dim}); "
                                 f"got {tuple(x.shape)}")
            parts.append(self.normalizer.normalize(key, x))
        if not parts:
            return torch.zeros(batch_size, self.cfg.obs_steps, 0, device=self.device)
        return torch.cat(parts, dim=-1)

    def _crop_obs(self, obs: Mapping, future_obs: Mapping | None, random: bool,
                  generator: torch.Generator | None) -> tuple[dict, dict | None, int]:
        """Crops o_t's frames and o_{t+k} with the SAME window per sample and camera (temporal-consistent
        crop, Sec. 4.1); centre crop unless ``random``. Returns {key: (B*T, 3, c, c)}, {key: (B, 3, c, c)}."""
        cfg, batch = self.cfg, None
        now, fut = {}, ({} if future_obs is not None else None)
        for key in cfg.image_keys:
            frames = self._images(obs, key, "obs", with_time=True)
            if batch is None:
                batch = frames.shape[0]
            elif frames.shape[0] != batch:
                raise ValueError(f"obs[{key!r}] has batch {frames.shape[0]}, other keys have {batch}")
            if future_obs is not None:
                f = self._images(future_obs, key, "future_obs", with_time=False)
                if f.shape[0] != batch:
                    raise ValueError(f"future_obs[{key!r}] has batch {f.shape[0]}, obs has {batch}")
                frames = torch.cat([frames, f[:, None]], dim=1)
            top, left = crop_windows(batch, cfg.image_size, cfg.crop_size, random, generator, frames.device)
            crops = self._pixels(key, crop_frames(frames, top, left, cfg.crop_size))
            now[key] = crops[:, :cfg.obs_steps].flatten(0, 1)
            if fut is not None:
                fut[key] = crops[:, cfg.obs_steps]
        return now, fut, batch

    def _crop_future(self, future_obs: Mapping) -> dict:
        cfg, out = self.cfg, {}
        for key in cfg.image_keys:
            f = self._images(future_obs, key, "future_obs", with_time=False)
            top, left = crop_windows(f.shape[0], cfg.image_size, cfg.crop_size, False, None, f.device)
            out[key] = self._pixels(key, crop_frames(f[:, None], top, left, cfg.crop_size)[:, 0])
        return out

    def _pixels(self, key: str, frames: Tensor) -> Tensor:
        """uint8 (..., h, w, 3) -> float (..., 3, h, w) as the encoder takes it (``ModelConfig.image_norm``)."""
        if self.image_normalizer is None:
            return to_chw_float(frames)
        return self.image_normalizer.normalize(key, frames.float().div_(255.0)).movedim(-1, -3)

    def _noise(self, shape: tuple, generator: torch.Generator | None, like: Tensor) -> Tensor:
        gen_device = generator.device if generator is not None else like.device
        return torch.randn(shape, generator=generator, device=gen_device).to(like.device, like.dtype)

    def _actions(self, batch: Mapping) -> Tensor:
        if "action" not in batch:
            raise KeyError("batch lacks 'action' (B, H, A), the unnormalised expert chunk")
        a = self._as_tensor(batch["action"], "batch['action']").float()
        want = (self.cfg.horizon, self.cfg.action_dim)
        if a.dim() != 3 or tuple(a.shape[1:]) != want:
            raise ValueError(f"batch['action'] must have shape (B, {want[0]}, {want[1]}); got {tuple(a.shape)}")
        return self.normalizer.normalize("action", a)

# ----------------------------------------------------------------------------------------------------------
# Initialisation
# ----------------------------------------------------------------------------------------------------------


def init_weights(module: nn.Module) -> None:
    """N(0, 0.02) linears and zero biases (DP / MIP transformer init); Kaiming convs; unit norms."""
    if isinstance(module, nn.Linear):
        nn.init.normal_(module.weight, std=0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.Conv2d):
        nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
    elif isinstance(module, (nn.LayerNorm, nn.GroupNorm)):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)
    for name in ("action_pos", "future_pos", "future_type", "cond_pos", "pos_emb", "cond_pos_emb"):
        p = getattr(module, name, None)
        if isinstance(p, nn.Parameter):
            nn.init.normal_(p, std=0.02)


def reset_linears(*modules: nn.Module) -> None:
    """Give the observation path's linears back PyTorch's fan-in-scaled default init.

    N(0, 0.02) is the init of a Transformer at width 384 and more (GPT, DP, MIP); diffusion_policy leaves its
    observation encoder at the default. On the observation path of a narrow model (the CPU presets) 0.02 shrinks
    Embed_o(c) to about 1% of the memory's time token and training sits on a plateau: on PushT (cpu preset,
    2k steps) the first-step action loss fell to 0.040 with it against 0.124 without (docs/training.md).
    """
    for module in modules:
        for m in module.modules():
            if isinstance(m, nn.Linear):
                m.reset_parameters()
