"""The Diffusion Policy arm (paper Sec. 4.2, 4.4): DP's transformer denoiser with DDPM epsilon prediction.

Follows the structure of Diffusion Policy's ``TransformerForDiffusion`` (time token + one token per observation
frame -> condition MLP -> memory; H noisy-action tokens in a causal pre-norm decoder with cross-attention) and its
robomimic image encoder (ResNet-18 with GroupNorm, spatial-softmax keypoints, a linear layer per camera).
Width 384 and 8 layers make it capacity-matched with JEPA Policy: 42.58 M on Tool Hang (paper 42.6 M).
Sampling uses diffusers' ``DDPMScheduler``: 100 training steps, any number of inference steps.
"""
from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from jepa_policy.config import ModelConfig
from jepa_policy.blocks import BasePolicyModel, ResNet18GN, SharedBlock, init_weights, reset_linears, sinusoid


class SpatialSoftmax(nn.Module):
    """Keypoints: a 1x1 conv to K maps, softmax over space, expected (x, y) in [-1, 1] -> (N, 2K)."""

    def __init__(self, channels: int, keypoints: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, keypoints, 1)

    def forward(self, fmap: Tensor) -> Tensor:
        n, _, h, w = fmap.shape
        attn = F.softmax(self.conv(fmap).flatten(2), dim=-1)                  # (N, K, h*w)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h, device=fmap.device, dtype=attn.dtype),
                                torch.linspace(-1, 1, w, device=fmap.device, dtype=attn.dtype), indexing="ij")
        x = (attn * xs.reshape(1, 1, -1)).sum(-1)
        y = (attn * ys.reshape(1, 1, -1)).sum(-1)
        return torch.stack([x, y], dim=-1).reshape(n, -1)


class CameraKeypointEncoder(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.backbone = ResNet18GN(cfg.encoder_width)
        self.keypoints = SpatialSoftmax(self.backbone.out_dim, cfg.diffusion_keypoints)
        self.proj = nn.Linear(2 * cfg.diffusion_keypoints, cfg.diffusion_feature_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(self.keypoints(self.backbone.feature_map(x)))


class DiffusionObsEncoder(nn.Module):
    """Per-camera keypoint features concatenated with the normalised low-dim inputs, one vector per frame."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.camera_keys = cfg.image_keys
        self.cameras = nn.ModuleDict({c: CameraKeypointEncoder(cfg) for c in cfg.cameras})
        self.out_dim = cfg.diffusion_feature_dim * len(cfg.cameras) + cfg.lowdim_dim

    def rgb(self, images: Mapping[str, Tensor]) -> Tensor:
        return torch.cat([net(images[key]) for key, net in zip(self.camera_keys, self.cameras.values())], dim=-1)

    def forward(self, images: Mapping[str, Tensor], lowdim: Tensor) -> Tensor:
        return torch.cat([self.rgb(images), lowdim], dim=-1)


class DiffusionTransformer(nn.Module):
    """epsilon_theta(a_k, k, obs): one denoising pass."""

    def __init__(self, cfg: ModelConfig, obs_dim: int):
        super().__init__()
        w, h, t_cond = cfg.width, cfg.horizon, 1 + cfg.obs_steps
        self.width = w
        self.input_emb = nn.Linear(cfg.action_dim, w)
        self.pos_emb = nn.Parameter(torch.zeros(1, h, w))
        self.cond_obs_emb = nn.Linear(obs_dim, w)
        self.cond_pos_emb = nn.Parameter(torch.zeros(1, t_cond, w))
        self.cond_encoder = nn.Sequential(nn.Linear(w, cfg.ffn_mult * w), nn.Mish(), nn.Linear(cfg.ffn_mult * w, w))
        self.blocks = nn.ModuleList(SharedBlock(w, cfg.heads, cfg.ffn_mult, cfg.dropout) for _ in range(cfg.layers))
        self.ln_f = nn.LayerNorm(w)
        self.head = nn.Linear(w, cfg.action_dim)
        # DP's masks: action token i sees actions <= i, the time token and observation frames <= i.
        self.register_buffer("self_mask", torch.ones(h, h, dtype=torch.bool).tril(), persistent=False)
        t_idx, s_idx = torch.meshgrid(torch.arange(h), torch.arange(t_cond), indexing="ij")
        self.register_buffer("memory_mask", t_idx >= s_idx - 1, persistent=False)

    def forward(self, sample: Tensor, timestep: Tensor, cond: Tensor) -> Tensor:
        time_token = sinusoid(timestep.float(), self.width).to(sample.dtype)[:, None]
        memory = self.cond_encoder(torch.cat([time_token, self.cond_obs_emb(cond)], dim=1) + self.cond_pos_emb)
        x = self.input_emb(sample) + self.pos_emb
        for block in self.blocks:
            x = block(x, memory, self.self_mask, self.memory_mask)
        return self.head(self.ln_f(x))


class DiffusionPolicyModel(BasePolicyModel):
    """Diffusion Policy with the shared model API: compute_loss, predict (DDPM sampling), encode_future."""

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        if cfg.arm != "diffusion":
            raise ValueError(f"DiffusionPolicyModel builds arm 'diffusion', not {cfg.arm!r}; use build_model(cfg)")
        self.encoder = DiffusionObsEncoder(cfg)
        self.denoiser = DiffusionTransformer(cfg, self.encoder.out_dim)
        # diffusers pulls in torch._dynamo (about 2 s of import); only models of this arm pay for it
        from diffusers import DDPMScheduler

        # DP's DDPM configuration: squared-cosine betas, epsilon prediction, clipped x0 (actions live in [-1, 1]).
        self.scheduler = DDPMScheduler(num_train_timesteps=cfg.diffusion_train_steps,
                                       beta_schedule="squaredcos_cap_v2", variance_type="fixed_small",
                                       clip_sample=True, prediction_type="epsilon")
        self.apply(init_weights)
        reset_linears(self.encoder)

    @property
    def future_dim(self) -> int:
        """Size of ``encode_future``'s output: the per-camera keypoint features (DP predicts no future)."""
        return self.cfg.diffusion_feature_dim * len(self.cfg.cameras)

    def _condition(self, obs: Mapping, random_crop: bool, generator) -> Tensor:
        images, _, b = self._crop_obs(obs, None, random_crop, generator)
        lowdim = self._lowdim(obs, b)
        return self.encoder(images, lowdim.flatten(0, 1)).view(b, self.cfg.obs_steps, -1)

    def step(self, sample: Tensor, timestep: Tensor, cond: Tensor) -> Tensor:
        """One denoising network pass."""
        return self.denoiser(sample, timestep, cond)

    def compute_loss(self, batch: Mapping, generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        """DDPM epsilon-prediction MSE at a uniformly drawn timestep."""
        for key in ("obs", "action"):
            if key not in batch:
                raise KeyError(f"batch lacks {key!r}; expected keys obs, action (future_obs is ignored by DP)")
        cond = self._condition(batch["obs"], self.training, generator)
        a = self._actions(batch)
        if a.shape[0] != cond.shape[0]:
            raise ValueError(f"batch['action'] has batch {a.shape[0]}, obs has {cond.shape[0]}")
        noise = self._noise(a.shape, generator, a)
        gen_device = generator.device if generator is not None else a.device
        t = torch.randint(0, self.cfg.diffusion_train_steps, (a.shape[0],), generator=generator,
                          device=gen_device).to(a.device)
        noisy = self.scheduler.add_noise(a, noise, t)
        loss = F.mse_loss(self.step(noisy, t, cond), noise)
        return loss, {"loss": float(loss.detach()), "loss_act": float(loss.detach())}

    @torch.no_grad()
    def predict(self, obs: Mapping, want_future: bool = True, num_inference_steps: int | None = None,
                generator: torch.Generator | None = None) -> tuple[Tensor, None]:
        """DDPM sampling from Gaussian noise with ``cfg.diffusion_infer_steps`` (or ``num_inference_steps``)
        denoiser passes; centre crop. -> (actions (B, H, A) unnormalised float32, None)."""
        steps = num_inference_steps or self.cfg.diffusion_infer_steps
        if not 1 <= steps <= self.cfg.diffusion_train_steps:
            raise ValueError(f"num_inference_steps={steps} must lie in [1, {self.cfg.diffusion_train_steps}]")
        cond = self._condition(obs, False, None)
        b = cond.shape[0]
        sample = self._noise((b, self.cfg.horizon, self.cfg.action_dim), generator, cond)
        # Timesteps stay on the CPU for the scheduler's table look-ups (as in DP); the network gets a device copy.
        self.scheduler.set_timesteps(steps)
        for t in self.scheduler.timesteps:
            eps = self.step(sample, t.to(cond.device).expand(b), cond)
            sample = self.scheduler.step(eps, t, sample, generator=generator).prev_sample
        return self.normalizer.unnormalize("action", sample.float()), None

    @torch.no_grad()
    def encode_future(self, future_obs: Mapping) -> Tensor:
        """The image features of frames (centre crop): {image_key: uint8 (B, H, W, 3)} -> (B, future_dim)."""
        return self.encoder.rgb(self._crop_future(future_obs)).float()
