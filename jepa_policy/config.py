"""ModelConfig: every number that shapes JEPA Policy's network, its comparison arms and its losses.

Defaults are the paper's (Sec. 3.2-3.4, 4.1, 4.2); ``ModelConfig.for_task`` fills the task-dependent shapes
from a ``jepa_envs.TaskSpec``. Why each architectural default has the value it has (so that the parameter
counts of the paper's Tool Hang configuration come out) is worked through in ``docs/model.md``.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from jepa_envs.tasks.spec import ObservationLayout, get_task_spec

ARMS = (
    "jepa",              # JEPA Policy: action tokens + one future token in one shared stack (Sec. 3.2)
    "mip",               # action-only MIP: no future token, lambda_z = 0 (Sec. 4.2)
    "dual_independent",  # shared conditioning path, two parameter-independent stacks (Sec. 4.2)
    "dual_cross",        # dual_independent + a bidirectional cross-attention block per layer (Sec. 4.2)
    "backcut",           # action tokens see the future token, future loss detached from the trunk (Sec. 4.5)
    "fwdcut",            # future loss shapes the trunk, action tokens cannot see the future token (Sec. 4.5)
    "sigreg",            # JEPA Policy + SIGReg isotropic-Gaussian regulariser on encoder latents (Sec. 4.7)
    "lambda_a0",         # JEPA Policy without the action loss: the collapse control (Sec. 4.9)
    "diffusion",         # Diffusion Policy transformer, DDPM epsilon prediction (Sec. 4.2)
)
LAMBDA_Z_MODES = ("adaptive", "fixed")
IMAGE_NORMS = (
    "unit",              # pixels / 255 in [0, 1], as Diffusion Policy and MIP feed a from-scratch ResNet
    "dataset",           # per-channel standardisation with the training frames' mean and std
)


@dataclass(frozen=True)
class ModelConfig(ObservationLayout):
    """Typed, validated configuration of one model of the family. Construct it with ``for_task``."""

    arm: str = "jepa"
    # --- task shapes (from the TaskSpec) ---
    cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
    image_size: int = 84
    crop_ratio: float = 0.9                  # random crop of 90% of the image (Sec. 4.1)
    image_norm: str = "unit"                 # pixel scaling into the encoder, one of IMAGE_NORMS
    lowdim: tuple[tuple[str, int], ...] = (("robot0_eef_pos", 3), ("robot0_eef_quat", 4),
                                           ("robot0_gripper_qpos", 2))
    action_dim: int = 10
    horizon: int = 10                        # H
    obs_steps: int = 2                       # observation history frames; one memory token per frame
    future_k: int = 4                        # env steps from the newest frame to the future target
    # --- network (Sec. 3.2) ---
    width: int = 384
    layers: int = 8
    heads: int = 6
    ffn_mult: int = 4                        # FFN width = ffn_mult * width
    time_emb_dim: int | None = None          # sinusoidal features per endpoint u, v; None -> width // 2
    encoder_width: int = 64                  # ResNet-18 stem width: 64 is the real ResNet-18
    dropout: float = 0.1
    # --- two-step objective (Sec. 3.3-3.4) ---
    tau: float = 0.9
    lambda_a: float = 1.0
    lambda_z_mode: str = "adaptive"
    rho: float = 0.10
    lambda_z_min: float = 1e-6
    lambda_z_max: float = 0.1
    lambda_z: float = 0.01                   # used when lambda_z_mode == "fixed"
    sigreg_weight: float = 0.09
    sigreg_slices: int = 256
    # --- dual-branch controls (Sec. 4.2) ---
    dual_future_layers: int | None = None    # None -> layers (8): dual_cross pairs layer i of both stacks
    dual_future_width: int | None = None     # None -> width // 2 (192); see docs/model.md
    # --- Diffusion Policy arm (Sec. 4.2, 4.4) ---
    diffusion_train_steps: int = 100
    diffusion_infer_steps: int = 100
    diffusion_keypoints: int = 32            # spatial-softmax keypoints per camera
    diffusion_feature_dim: int = 64          # per-camera feature after the keypoints
    # --- a pretrained image encoder (the paper's DINO variant is one; train.load_encoder_weights) ---
    encoder_weights: str = ""                # local file the training run initialised the encoder from ("" = none)
    encoder_weights_sha256: str = ""         # its content hash, recorded when the run started
    encoder_key_map: tuple[tuple[str, str], ...] = ()   # (source prefix, our prefix) pairs applied to its keys
    freeze_encoder: bool = False             # keep the encoder fixed (its target z_{t+k} then moves no more)

    extra: dict = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        # Accept lists from JSON/YAML so from_dict round-trips.
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "lowdim", tuple((str(k), int(d)) for k, d in self.lowdim))
        object.__setattr__(self, "encoder_key_map", tuple((str(a), str(b)) for a, b in self.encoder_key_map))
        # Derived defaults that reproduce the paper's counts at width 384 and scale with small CPU configs.
        for name, value in (("time_emb_dim", self.width // 2), ("dual_future_width", self.width // 2),
                            ("dual_future_layers", self.layers)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        self.validate()

    # ----- derived shapes -----
    @property
    def crop_size(self) -> int:
        return int(round(self.crop_ratio * self.image_size))

    @property
    def camera_feature_dim(self) -> int:
        """Pooled ResNet-18 feature per camera (512 for the real ResNet-18)."""
        return 8 * self.encoder_width

    @property
    def future_dim(self) -> int:
        """d_z: the concatenated per-camera pooled features, E_rgb(o) (Sec. 3.1)."""
        return self.camera_feature_dim * len(self.cameras)

    @property
    def has_future_token(self) -> bool:
        return self.arm not in ("mip", "diffusion")

    @property
    def is_dual(self) -> bool:
        return self.arm in ("dual_independent", "dual_cross")

    @property
    def effective_lambda_a(self) -> float:
        return 0.0 if self.arm == "lambda_a0" else self.lambda_a

    # ----- validation -----
    def validate(self) -> None:
        """Raise ValueError naming the bad field and the fix."""
        def bad(msg: str) -> None:
            raise ValueError(f"ModelConfig: {msg}")

        if self.arm not in ARMS:
            bad(f"arm={self.arm!r} is unknown; choose one of {', '.join(ARMS)}")
        if self.image_norm not in IMAGE_NORMS:
            bad(f"image_norm={self.image_norm!r} is unknown; choose one of {', '.join(IMAGE_NORMS)}")
        if self.freeze_encoder and not self.encoder_weights:
            bad("freeze_encoder needs encoder_weights: a frozen random encoder learns nothing")
        if self.encoder_weights and self.arm == "diffusion":
            bad("encoder_weights load a JEPA-family ResNet encoder; the diffusion arm has its own encoder")
        if self.lambda_z_mode not in LAMBDA_Z_MODES:
            bad(f"lambda_z_mode={self.lambda_z_mode!r}; choose 'adaptive' or 'fixed'")
        if not self.cameras:
            bad("cameras is empty; the encoder needs at least one RGB camera")
        if len(set(self.cameras)) != len(self.cameras):
            bad(f"cameras {self.cameras} has duplicates")
        for k, d in self.lowdim:
            if d <= 0:
                bad(f"low-dim key {k!r} has dimension {d}; dimensions must be positive")
            if "." in k:
                bad(f"low-dim key {k!r} contains '.', which torch module names forbid; rename it")
        for name in ("image_size", "action_dim", "horizon", "obs_steps", "future_k", "width", "layers",
                     "heads", "ffn_mult", "time_emb_dim", "encoder_width", "dual_future_layers",
                     "dual_future_width", "diffusion_train_steps", "diffusion_infer_steps",
                     "diffusion_keypoints", "diffusion_feature_dim", "sigreg_slices"):
            if int(getattr(self, name)) <= 0:
                bad(f"{name}={getattr(self, name)} must be a positive integer")
        if not 0.0 < self.crop_ratio <= 1.0:
            bad(f"crop_ratio={self.crop_ratio} must lie in (0, 1]")
        if self.crop_size < 8:
            bad(f"image_size={self.image_size} with crop_ratio={self.crop_ratio} gives a {self.crop_size}px "
                "crop; ResNet-18 needs at least 8px: raise image_size or crop_ratio")
        if self.width % self.heads:
            bad(f"width={self.width} is not divisible by heads={self.heads}")
        if self.time_emb_dim % 2:
            bad(f"time_emb_dim={self.time_emb_dim} must be even (sin and cos halves)")
        if not 0.0 < self.tau < 1.0:
            bad(f"tau={self.tau} must lie strictly between 0 and 1 (two intervals (0,tau) and (tau,1))")
        if self.lambda_a < 0 or self.lambda_z < 0 or self.rho < 0 or self.sigreg_weight < 0:
            bad("lambda_a, lambda_z, rho and sigreg_weight must be non-negative")
        if not 0.0 < self.lambda_z_min <= self.lambda_z_max:
            bad(f"need 0 < lambda_z_min ({self.lambda_z_min}) <= lambda_z_max ({self.lambda_z_max})")
        if not 0.0 <= self.dropout < 1.0:
            bad(f"dropout={self.dropout} must lie in [0, 1)")
        if self.is_dual and self.dual_future_width % self.heads:
            bad(f"dual_future_width={self.dual_future_width} is not divisible by heads={self.heads}")
        if self.arm == "dual_cross" and self.dual_future_layers != self.layers:
            bad(f"dual_cross pairs layer i of both stacks, so dual_future_layers ({self.dual_future_layers}) "
                f"must equal layers ({self.layers})")
        if self.diffusion_infer_steps > self.diffusion_train_steps:
            bad(f"diffusion_infer_steps={self.diffusion_infer_steps} exceeds diffusion_train_steps="
                f"{self.diffusion_train_steps}")

    # ----- construction -----
    @classmethod
    def for_task(cls, spec: Any, arm: str = "jepa", **overrides: Any) -> "ModelConfig":
        """The paper's configuration for a ``jepa_envs.TaskSpec`` (or its name), with ``overrides`` applied.

        ``lambda_a0`` runs with a fixed lambda_z = lambda_z_max: with lambda_a = 0 the adaptive ratio of
        Eq. (ratio_mode) would pin lambda_z at its floor, and the arm exists to let the future loss train alone.
        """
        if isinstance(spec, str):
            spec = get_task_spec(spec)
        base = dict(
            arm=arm, cameras=tuple(spec.cameras), image_size=int(spec.image_size), lowdim=tuple(spec.lowdim),
            action_dim=int(spec.action_dim), horizon=int(spec.horizon), obs_steps=int(spec.obs_steps),
            future_k=int(spec.future_k),
        )
        if arm == "lambda_a0":
            base.update(lambda_z_mode="fixed", lambda_z=cls.lambda_z_max)
        unknown = set(overrides) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"ModelConfig.for_task: unknown override(s) {sorted(unknown)}; "
                             f"valid fields: {', '.join(f.name for f in fields(cls))}")
        base.update(overrides)
        return cls(**base)

    def replace(self, **changes: Any) -> "ModelConfig":
        return replace(self, **changes)

    def to_dict(self) -> dict:
        """JSON-serialisable dict (tuples become lists); ``from_dict`` inverts it."""
        d = asdict(self)
        d["cameras"] = list(self.cameras)
        d["lowdim"] = [[k, v] for k, v in self.lowdim]
        d["encoder_key_map"] = [[a, b] for a, b in self.encoder_key_map]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"ModelConfig.from_dict: unknown key(s) {sorted(unknown)}; was the file written by "
                             "a different version of jepa_policy?")
        return cls(**d)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)
