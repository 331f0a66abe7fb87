"""JEPA Policy, top to bottom (paper Sec. 3.2-3.4): encoder, conditioning memory, shared stack, heads, arms.

One family told apart by ``ModelConfig.arm``:
  jepa              H action tokens + one future token in one unmasked self-attention stack
  mip               the same without the future token and with lambda_z = 0
  backcut           action tokens attend to the future token; the future head reads a detached trunk output
  fwdcut            the future token shapes the trunk; action tokens may not attend to it
  sigreg            jepa + SIGReg on the encoder latents c_t
  lambda_a0         jepa without the action loss
  dual_independent  shared conditioning path -> action stack (width 384) and future stack (width 192), no link
  dual_cross        dual_independent + a bidirectional cross-attention block at every layer
  diffusion         Diffusion Policy transformer (jepa_policy/diffusion.py), built by ``build_model`` too.

Tensor conventions: images arrive as uint8 (B, T, H, W, 3) and become float [0, 1] (N, 3, h, w) inside;
actions and low-dim inputs are mapped to [-1, 1] by ``model.normalizer``; c is (B, T_obs, width).
A network pass F_theta (one ``step`` call) never re-runs the image encoder: ``predict`` encodes once
and both passes reuse c.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from jepa_policy.config import ModelConfig
from jepa_policy.losses import sigreg, two_step_terms
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


class ObservationEncoder(nn.Module):
    """E: one ResNet-18 per camera -> z = E_rgb(o) (concatenated pooled features); c = Fuse([z, s]) (Sec. 3.1)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.camera_keys = cfg.image_keys
        self.cameras = nn.ModuleDict({c: ResNet18GN(cfg.encoder_width) for c in cfg.cameras})
        # Fuse is a 2-layer MLP as in MIP's released encoder; it brings E to the paper's 22.90 M (docs/model.md).
        self.fuse = nn.Sequential(nn.Linear(cfg.future_dim + cfg.lowdim_dim, cfg.width), nn.LeakyReLU(),
                                  nn.Linear(cfg.width, cfg.width))

    def rgb(self, images: Mapping[str, Tensor]) -> Tensor:
        """E_rgb: {image_key: (N, 3, h, w) float} -> z (N, d_z), cameras in config order."""
        return torch.cat([net(images[key]) for key, net in zip(self.camera_keys, self.cameras.values())], dim=-1)

    def forward(self, images: Mapping[str, Tensor], lowdim: Tensor) -> Tensor:
        """-> c (N, width): the conditioning representation, which also carries proprioception."""
        return self.fuse(torch.cat([self.rgb(images), lowdim], dim=-1))


# ----------------------------------------------------------------------------------------------------------
# Conditioning memory M = Enc([TimeEmb(u, v), Embed_o(c_t)]) (Sec. 3.2, Eq. memory)
# ----------------------------------------------------------------------------------------------------------


def sinusoid(x: Tensor, dim: int) -> Tensor:
    """Transformer sinusoidal features of a scalar per sample: (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=x.device, dtype=torch.float32) / half)
    angles = x.float()[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class TimeEmbedding(nn.Module):
    """TimeEmb(u, v): the two interval endpoints, each embedded sinusoidally, form one memory token.

    With 2 * time_emb_dim == width (the paper's configuration) it has no parameters, as in MIP's released code;
    otherwise a linear map brings the features to the model width.
    """

    SCALE = 1000.0  # u, v in [0, 1] are spread over DDPM-like timestep magnitudes so the features differ

    def __init__(self, time_emb_dim: int, width: int):
        super().__init__()
        self.dim = time_emb_dim
        self.proj = nn.Identity() if 2 * time_emb_dim == width else nn.Linear(2 * time_emb_dim, width)

    def forward(self, u: Tensor, v: Tensor) -> Tensor:
        feats = torch.cat([sinusoid(u * self.SCALE, self.dim), sinusoid(v * self.SCALE, self.dim)], dim=-1)
        return self.proj(feats)


class MemoryEncoder(nn.Module):
    """Embed_o, TimeEmb, learned memory positions and Enc (DP's condition MLP). One memory token per frame."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        w = cfg.width
        self.obs_embed = nn.Linear(w, w)
        self.time_embed = TimeEmbedding(cfg.time_emb_dim, w)
        self.cond_pos = nn.Parameter(torch.zeros(1 + cfg.obs_steps, w))
        self.net = nn.Sequential(nn.Linear(w, cfg.ffn_mult * w), nn.Mish(), nn.Linear(cfg.ffn_mult * w, w))
        # Dual-branch arms: the narrower future stack reads the same memory through an adapter (Sec. 4.2).
        self.future_adapter = nn.Linear(w, cfg.dual_future_width) if cfg.is_dual else None

    def embed_obs(self, c: Tensor) -> Tensor:
        """Embed_o(c): (B, T_obs, width); computed once per decision and reused by both passes."""
        return self.obs_embed(c)

    def forward(self, obs_tokens: Tensor, u: Tensor, v: Tensor) -> Tensor:
        tokens = torch.cat([self.time_embed(u, v).to(obs_tokens.dtype)[:, None], obs_tokens], dim=1)
        return self.net(tokens + self.cond_pos)


# ----------------------------------------------------------------------------------------------------------
# Transformer pieces
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


class Transformer(nn.Module):
    """T_theta: a stack of SharedBlocks and the final LayerNorm shared by every token type."""

    def __init__(self, dim: int, layers: int, heads: int, ffn_mult: int, dropout: float):
        super().__init__()
        self.blocks = nn.ModuleList(SharedBlock(dim, heads, ffn_mult, dropout) for _ in range(layers))
        self.ln_f = nn.LayerNorm(dim)

    def forward(self, x: Tensor, memory: Tensor, self_mask: Tensor | None = None,
                memory_mask: Tensor | None = None) -> Tensor:
        for block in self.blocks:
            x = block(x, memory, self_mask, memory_mask)
        return self.ln_f(x)


class CrossBranchBlock(nn.Module):
    """Dual-cross: action tokens read the future branch and the future token reads the action branch."""

    def __init__(self, dim_a: int, dim_f: int, heads: int, dropout: float):
        super().__init__()
        self.norm_a_query, self.norm_f_context = nn.LayerNorm(dim_a), nn.LayerNorm(dim_f)
        self.norm_f_query, self.norm_a_context = nn.LayerNorm(dim_f), nn.LayerNorm(dim_a)
        self.a_from_f = Attention(dim_a, heads, kv_dim=dim_f, dropout=dropout)
        self.f_from_a = Attention(dim_f, heads, kv_dim=dim_a, dropout=dropout)
        self.drop = nn.Dropout(dropout)

    def forward(self, a: Tensor, f: Tensor) -> tuple[Tensor, Tensor]:
        da = self.a_from_f(self.norm_a_query(a), self.norm_f_context(f))
        df = self.f_from_a(self.norm_f_query(f), self.norm_a_context(a))
        return a + self.drop(da), f + self.drop(df)


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
# JEPA Policy and its two-step arms
# ----------------------------------------------------------------------------------------------------------


class PolicyModel(BasePolicyModel):
    """F_theta(o, a_in, z_in, u, v) -> (a_hat, z_hat) and its two-step training and inference (Sec. 3.2-3.4)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        if cfg.arm == "diffusion":
            raise ValueError("PolicyModel does not build the diffusion arm; use build_model(cfg)")
        w, h = cfg.width, cfg.horizon
        self.encoder = ObservationEncoder(cfg)
        self.memory = MemoryEncoder(cfg)
        # H action tokens q_a = Embed_a(a_in) + p_{1:H}
        self.action_embed = nn.Linear(cfg.action_dim, w)
        self.action_pos = nn.Parameter(torch.zeros(h, w))
        self.action_head = nn.Linear(w, cfg.action_dim)                        # h_a
        if cfg.has_future_token:
            wf = cfg.dual_future_width if cfg.is_dual else w
            # one future token q_z = Embed_z(z_in) + e_z + p_{H+1}
            self.future_embed = nn.Linear(cfg.future_dim, wf)
            self.future_type = nn.Parameter(torch.zeros(wf))                   # e_z
            self.future_pos = nn.Parameter(torch.zeros(wf))                    # p_{H+1}
            self.future_head = nn.Linear(wf, cfg.future_dim)                   # h_z
        if cfg.is_dual:
            self.action_stack = Transformer(w, cfg.layers, cfg.heads, cfg.ffn_mult, cfg.dropout)
            self.future_stack = Transformer(cfg.dual_future_width, cfg.dual_future_layers, cfg.heads,
                                            cfg.ffn_mult, cfg.dropout)
            self.cross_blocks = (nn.ModuleList(CrossBranchBlock(w, cfg.dual_future_width, cfg.heads, cfg.dropout)
                                               for _ in range(cfg.layers)) if cfg.arm == "dual_cross" else None)
        else:
            self.trunk = Transformer(w, cfg.layers, cfg.heads, cfg.ffn_mult, cfg.dropout)
        # Fwd-cut (Sec. 4.5): action tokens may not attend to the future token; it still attends to them.
        mask = None
        if cfg.arm == "fwdcut":
            mask = torch.ones(h + 1, h + 1, dtype=torch.bool)
            mask[:h, h] = False
        self.register_buffer("self_attn_mask", mask, persistent=False)
        self.apply(init_weights)
        reset_linears(self.encoder, self.memory)

    @property
    def future_dim(self) -> int:
        """d_z, the size of E_rgb(o) and of z_hat."""
        return self.cfg.future_dim

    # ----- one network pass F_theta -----
    def step(self, obs_tokens: Tensor, a_in: Tensor, z_in: Tensor | None, u: Tensor, v: Tensor,
             want_future: bool = True) -> tuple[Tensor, Tensor | None]:
        """One pass of F_theta with Embed_o(c) precomputed: normalised (a_hat (B,H,A), z_hat (B,d_z) or None)."""
        cfg = self.cfg
        memory = self.memory(obs_tokens, u, v)
        q_a = self.action_embed(a_in) + self.action_pos
        if not cfg.has_future_token:
            return self.action_head(self.trunk(q_a, memory)), None
        if z_in is None:
            raise ValueError(f"arm {cfg.arm!r} has a future token: pass z_in (zeros for the first step)")
        q_z = (self.future_embed(z_in) + self.future_type + self.future_pos)[:, None]
        if cfg.is_dual:
            return self._dual_step(q_a, q_z, memory, want_future)
        y = self.trunk(torch.cat([q_a, q_z], dim=1), memory, self_mask=self.self_attn_mask)
        a_hat = self.action_head(y[:, :cfg.horizon])
        if not want_future:
            return a_hat, None
        y_z = y[:, cfg.horizon]
        # Back-cut (Sec. 4.5): the future loss reaches h_z only, never the shared trunk.
        return a_hat, self.future_head(y_z.detach() if cfg.arm == "backcut" else y_z)

    def _dual_step(self, q_a: Tensor, q_z: Tensor, memory: Tensor, want_future: bool):
        memory_f = self.memory.future_adapter(memory)
        if self.cross_blocks is None:
            a_hat = self.action_head(self.action_stack(q_a, memory))
            if not want_future:
                return a_hat, None
            return a_hat, self.future_head(self.future_stack(q_z, memory_f)[:, 0])
        a, f = q_a, q_z
        for block_a, block_f, cross in zip(self.action_stack.blocks, self.future_stack.blocks, self.cross_blocks):
            a, f = block_a.self_attend(a), block_f.self_attend(f)
            a, f = cross(a, f)
            a = block_a.feed_forward(block_a.read_memory(a, memory))
            f = block_f.feed_forward(block_f.read_memory(f, memory_f))
        a_hat = self.action_head(self.action_stack.ln_f(a))
        return a_hat, (self.future_head(self.future_stack.ln_f(f)[:, 0]) if want_future else None)

    def _time(self, value: float, n: int, like: Tensor) -> Tensor:
        return torch.full((n,), value, device=like.device, dtype=torch.float32)

    # ----- training (Sec. 3.3-3.4) -----
    def compute_loss(self, batch: Mapping, generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        """Two-step loss of one minibatch: (scalar loss, {name: float}); see the module docstring for shapes."""
        terms, parts = self.loss_terms(batch, generator)
        loss = sum(terms.values())
        parts["loss"] = loss.detach()
        names = list(parts)
        values = torch.stack([parts[n].float() for n in names]).tolist()   # one device sync
        return loss, dict(zip(names, values))

    def loss_terms(self, batch: Mapping, generator: torch.Generator | None = None) -> tuple[dict, dict]:
        """The weighted loss terms with their graphs ({"act", "future", "sigreg"} as present) and the detached
        parts. ``compute_loss`` sums the terms; ``gradient_share`` differentiates them one at a time."""
        cfg = self.cfg
        for key in ("obs", "action") + (("future_obs",) if cfg.has_future_token else ()):
            if key not in batch:
                raise KeyError(f"batch lacks {key!r}; expected keys obs, future_obs, action")
        images, future_images, b = self._crop_obs(batch["obs"], batch.get("future_obs") if cfg.has_future_token
                                                  else None, self.training, generator)
        lowdim = self._lowdim(batch["obs"], b)
        a = self._actions(batch)
        if a.shape[0] != b:
            raise ValueError(f"batch['action'] has batch {a.shape[0]}, obs has {b}")
        c = self.encoder(images, lowdim.flatten(0, 1)).view(b, cfg.obs_steps, cfg.width)
        obs_tokens = self.memory.embed_obs(c)
        tau = cfg.tau
        # The two steps are decoupled in training (Sec. 3.4), so both run as one batch of 2B.
        a_tilde = a + (1.0 - tau) * self._noise(a.shape, generator, a)
        a_in = torch.cat([torch.zeros_like(a), a_tilde])
        z = z_in = None
        if cfg.has_future_token:
            with torch.no_grad():                   # sg(z_{t+k}) from the live encoder (Sec. 3.3)
                z = self.encoder.rgb(future_images)
            z_tilde = z + (1.0 - tau) * self._noise(z.shape, generator, z)
            z_in = torch.cat([torch.zeros_like(z), z_tilde])
        u = torch.cat([self._time(0.0, b, a), self._time(tau, b, a)])
        v = torch.cat([self._time(tau, b, a), self._time(1.0, b, a)])
        a_hat, z_hat = self.step(obs_tokens.repeat(2, 1, 1), a_in, z_in, u, v)
        # Losses in float32 even under bf16 autocast: the NMSE divides by the target's RMS.
        a_hat = a_hat.float()
        z_hat, z = (None, None) if z_hat is None else (z_hat.float(), z.float())
        act_term, future_term, parts = two_step_terms(
            a_hat[:b], a_hat[b:], a, tau,
            z_hat0=None if z_hat is None else z_hat[:b], z_hat1=None if z_hat is None else z_hat[b:], z=z,
            lambda_a=cfg.effective_lambda_a, lambda_z_mode=cfg.lambda_z_mode, lambda_z=cfg.lambda_z,
            rho=cfg.rho, lambda_z_min=cfg.lambda_z_min, lambda_z_max=cfg.lambda_z_max)
        terms = {"act": act_term}
        if future_term is not None:
            terms["future"] = future_term
        if cfg.arm == "sigreg":
            reg = sigreg(c.flatten(0, 1).float(), num_slices=cfg.sigreg_slices, generator=generator)
            terms["sigreg"] = cfg.sigreg_weight * reg
            parts["loss_sigreg"] = reg.detach()
        return terms, parts

    # ----- where the future objective acts (Sec. 4.5) -----
    def action_readout_parameters(self) -> list[nn.Parameter]:
        """The parameters that produce the action readout: the stack the action tokens run through, their
        embedding, positions and head (the shared trunk for single-stack arms, the action stack for dual)."""
        owners = ("action_stack" if self.cfg.is_dual else "trunk", "action_embed", "action_pos", "action_head")
        return [p for n, p in self.named_parameters() if n.split(".", 1)[0] in owners]

    def gradient_share(self, batch: Mapping, generator: torch.Generator | None = None) -> float:
        """Sec. 4.5: ||grad of lambda_z L_future|| / ||grad of lambda_a L_act|| on ``action_readout_parameters``
        (exactly 0 for dual_independent and backcut; 0 for arms without a future term)."""
        terms, _ = self.loss_terms(batch, generator)
        if "future" not in terms:
            return 0.0
        params = self.action_readout_parameters()

        def norm(term: Tensor, retain: bool) -> Tensor:
            grads = torch.autograd.grad(term, params, retain_graph=retain, allow_unused=True)
            squares = [g.float().pow(2).sum() for g in grads if g is not None]
            return torch.stack(squares).sum().sqrt() if squares else torch.zeros((), device=term.device)

        future = norm(terms["future"], retain=True)
        return float(future / norm(terms["act"], retain=False).clamp_min(1e-30))

    # ----- inference (Sec. 3.4, last equation) -----
    @torch.no_grad()
    def predict(self, obs: Mapping, want_future: bool = True) -> tuple[Tensor, Tensor | None]:
        """Two passes from one encoding: step 1 from zeros at (0, tau), step 2 fed step 1's outputs at (tau, 1),
        no noise, centre crop. -> (actions (B, H, A) unnormalised float32, z_hat (B, d_z) or None)."""
        cfg = self.cfg
        images, _, b = self._crop_obs(obs, None, False, None)
        lowdim = self._lowdim(obs, b)
        c = self.encoder(images, lowdim.flatten(0, 1)).view(b, cfg.obs_steps, cfg.width)
        obs_tokens = self.memory.embed_obs(c)
        ref = obs_tokens
        a0_in = torch.zeros(b, cfg.horizon, cfg.action_dim, device=ref.device, dtype=ref.dtype)
        z0_in = (torch.zeros(b, cfg.future_dim, device=ref.device, dtype=ref.dtype)
                 if cfg.has_future_token else None)
        a0, z0 = self.step(obs_tokens, a0_in, z0_in, self._time(0.0, b, ref), self._time(cfg.tau, b, ref))
        a1, z1 = self.step(obs_tokens, a0, z0, self._time(cfg.tau, b, ref), self._time(1.0, b, ref),
                           want_future=want_future)
        actions = self.normalizer.unnormalize("action", a1.float())
        return actions, (None if z1 is None else z1.float())

    @torch.no_grad()
    def encode_future(self, future_obs: Mapping) -> Tensor:
        """z = E_rgb(o_{t+k}) with centre crop: {image_key: uint8 (B, H, W, 3)} -> (B, d_z)."""
        return self.encoder.rgb(self._crop_future(future_obs)).float()


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


def build_model(cfg: ModelConfig) -> BasePolicyModel:
    """The model of ``cfg.arm``: PolicyModel for the two-step arms, DiffusionPolicyModel for ``diffusion``."""
    if cfg.arm == "diffusion":
        from jepa_policy.diffusion import DiffusionPolicyModel
        return DiffusionPolicyModel(cfg)
    return PolicyModel(cfg)
