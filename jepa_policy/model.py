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

The pieces every arm shares (ResNet-18 GN, the Transformer layer, crops, ``BasePolicyModel``) live in
``blocks.py``; the Diffusion Policy arm is ``diffusion.py``; ``build_model`` (the end of this file) picks by arm.

Tensor conventions: images arrive as uint8 (B, T, H, W, 3) and become float [0, 1] (N, 3, h, w) inside;
actions and low-dim inputs are mapped to [-1, 1] by ``model.normalizer``; c is (B, T_obs, width).
A network pass F_theta (one ``step`` call) never re-runs the image encoder: ``predict`` encodes once
and both passes reuse c.
"""
from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from jepa_policy.blocks import (Attention, BasePolicyModel, ResNet18GN, SharedBlock, init_weights, reset_linears,
                                sinusoid)
from jepa_policy.config import ModelConfig
from jepa_policy.diffusion import DiffusionPolicyModel
from jepa_policy.losses import sigreg, two_step_terms

# ----------------------------------------------------------------------------------------------------------
# Image encoder E: one ResNet-18 GN per camera (Sec. 3.2, 4.1)
# ----------------------------------------------------------------------------------------------------------


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

    def forward(self, images: Mapping[str, Tensor], lowdim: Tensor, with_rgb: bool = False):
        """-> c (N, width): the conditioning representation, which also carries proprioception; with ``with_rgb``
        also its E_rgb (N, d_z), from the same pass."""
        rgb = self.rgb(images)
        c = self.fuse(torch.cat([rgb, lowdim], dim=-1))
        return (c, rgb) if with_rgb else c

# ----------------------------------------------------------------------------------------------------------
# Conditioning memory M = Enc([TimeEmb(u, v), Embed_o(c_t)]) (Sec. 3.2, Eq. memory)
# ----------------------------------------------------------------------------------------------------------

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
        actions, z_hat, _ = self.predict_embedded(obs, want_future)
        return actions, z_hat

    @torch.no_grad()
    def predict_embedded(self, obs: Mapping, want_future: bool = True) -> tuple[Tensor, Tensor | None, Tensor]:
        """``predict`` and the newest frame's fused embedding c_t (B, width), which the runtime's embedding
        scores read (``jepa_policy/detectors.py``) at no extra network pass."""
        c, _ = self._encode(obs)
        actions, z_hat = self._two_steps(c, want_future)
        return actions, z_hat, c[:, -1].float()

    def _encode(self, obs: Mapping) -> tuple[Tensor, Tensor]:
        """Centre-cropped encoding of an observation history: (c (B, T, width), E_rgb (B, T, d_z))."""
        cfg = self.cfg
        images, _, b = self._crop_obs(obs, None, False, None)
        c, rgb = self.encoder(images, self._lowdim(obs, b).flatten(0, 1), with_rgb=True)
        return c.view(b, cfg.obs_steps, cfg.width), rgb.view(b, cfg.obs_steps, -1)

    def _two_steps(self, c: Tensor, want_future: bool) -> tuple[Tensor, Tensor | None]:
        cfg, b = self.cfg, c.shape[0]
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
    def representations(self, obs: Mapping) -> dict[str, Tensor]:
        """The views the collapse audit reads (Sec. 4.9), for the newest frame of each history:
        ``c_t`` the fused representation Fuse([E_rgb(o_t), s_t]) (width), ``e_rgb`` its pooled image features
        E_rgb(o_t) (d_z), and ``z_hat`` the refined future prediction (arms with a future token)."""
        c, rgb = self._encode(obs)
        out = {"c_t": c[:, -1].float(), "e_rgb": rgb[:, -1].float()}
        if self.cfg.has_future_token:
            out["z_hat"] = self._two_steps(c, want_future=True)[1]
        return out

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Named parts for the gradient-interaction audit (Sec. 4.5): the image encoder and fusion, the
        conditioning path M shared by both heads, the stack(s), and each head with its token embedding."""
        groups = {"encoder": ("encoder",), "conditioning": ("memory",),
                  "action_head": ("action_embed", "action_pos", "action_head"),
                  "future_head": ("future_embed", "future_type", "future_pos", "future_head")}
        groups.update({"action_stack": ("action_stack",), "future_stack": ("future_stack",),
                       "cross_blocks": ("cross_blocks",)} if self.cfg.is_dual else {"trunk": ("trunk",)})
        out = {name: [p for n, p in self.named_parameters() if n.split(".", 1)[0] in owners and p.requires_grad]
               for name, owners in groups.items()}
        return {name: params for name, params in out.items() if params}

    @torch.no_grad()
    def encode_future(self, future_obs: Mapping) -> Tensor:
        """z = E_rgb(o_{t+k}) with centre crop: {image_key: uint8 (B, H, W, 3)} -> (B, d_z)."""
        return self.encoder.rgb(self._crop_future(future_obs)).float()


def build_model(cfg: ModelConfig) -> BasePolicyModel:
    """The model of ``cfg.arm``: PolicyModel for the two-step arms, DiffusionPolicyModel for ``diffusion``."""
    if cfg.arm == "diffusion":
        return DiffusionPolicyModel(cfg)
    return PolicyModel(cfg)
