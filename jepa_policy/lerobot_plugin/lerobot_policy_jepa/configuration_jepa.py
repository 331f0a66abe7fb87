"""The LeRobot configuration of JEPA Policy: ``--policy.type=jepa`` and its fields.

The model fields are ``jepa_policy.config.ModelConfig``'s under the same names, with the paper's defaults
(``--policy.arm=mip`` trains the MIP arm); the task (``--policy.task``, a task of ``jepa-envs list``) names the
observation keys, the chunk length H, the future horizon k and the replanning cadence, which LeRobot's dataset
loader needs before the policy is built. The optimiser is the paper's (AdamW, cosine decay after a warm-up).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamWConfig
from lerobot.optim.schedulers import CosineDecayWithWarmupSchedulerConfig

from jepa_envs.tasks.spec import TaskSpec, get_task_spec
from jepa_policy.config import ModelConfig
from jepa_policy.lerobot_format import MODEL_FIELDS, check_features, model_config


@PreTrainedConfig.register_subclass("jepa")
@dataclass
class JEPAConfig(PreTrainedConfig):
    """JEPA Policy and its two-step comparison arms in LeRobot; the features must be the task's (checked)."""

    task: str = "PushTStandard"          # gym-pusht's Push-T, lerobot/pusht's layout
    arm: str = "jepa"                    # jepa | mip | dual_independent | dual_cross | backcut | fwdcut | ...
    n_obs_steps: int = 2
    horizon: int | None = None           # H; None: the task's
    n_action_steps: int | None = None    # actions executed per chunk; None: the task's (8)
    future_k: int | None = None          # env steps from the newest frame to z_hat's target; None: the task's
    # --- network and two-step objective (ModelConfig's own defaults, the paper's, read from it) ---
    width: int = ModelConfig.width
    layers: int = ModelConfig.layers
    heads: int = ModelConfig.heads
    ffn_mult: int = ModelConfig.ffn_mult
    time_emb_dim: int | None = ModelConfig.time_emb_dim
    encoder_width: int = ModelConfig.encoder_width
    dropout: float = ModelConfig.dropout
    crop_ratio: float = ModelConfig.crop_ratio
    image_norm: str = ModelConfig.image_norm
    tau: float = ModelConfig.tau
    lambda_a: float = ModelConfig.lambda_a
    lambda_z_mode: str = ModelConfig.lambda_z_mode
    rho: float = ModelConfig.rho
    lambda_z_min: float = ModelConfig.lambda_z_min
    lambda_z_max: float = ModelConfig.lambda_z_max
    lambda_z: float = ModelConfig.lambda_z
    sigreg_weight: float = ModelConfig.sigreg_weight
    sigreg_slices: int = ModelConfig.sigreg_slices
    dual_future_layers: int | None = ModelConfig.dual_future_layers
    dual_future_width: int | None = ModelConfig.dual_future_width
    # --- optimiser (Sec. 4.1) ---
    optimizer_lr: float = 1e-4
    optimizer_betas: tuple[float, float] = (0.9, 0.999)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-6
    optimizer_grad_clip_norm: float = 10.0
    scheduler_warmup_steps: int = 500
    scheduler_decay_steps: int = 300_000
    # The network scales its own inputs and outputs (statistics in its weights, as in our checkpoints), so
    # LeRobot's processors normalise nothing.
    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=lambda: {
        "VISUAL": NormalizationMode.IDENTITY, "STATE": NormalizationMode.IDENTITY,
        "ACTION": NormalizationMode.IDENTITY})

    def __post_init__(self) -> None:
        super().__post_init__()
        spec = self.task_spec()
        for name, value in (("horizon", spec.horizon), ("n_action_steps", spec.n_action_steps),
                            ("future_k", spec.future_k)):
            if getattr(self, name) is None:
                setattr(self, name, int(value))
        if not 1 <= self.n_action_steps <= self.horizon:
            raise ValueError(f"--policy.n_action_steps={self.n_action_steps} must lie in [1, horizon={self.horizon}]")
        # the model fields are checked by building the ModelConfig once, at the task's image size
        model_config(self.fields(), spec.image_size)

    def task_spec(self) -> TaskSpec:
        try:
            return get_task_spec(self.task)
        except KeyError as exc:
            raise ValueError(f"--policy.task={self.task!r} is not a task of this toolkit ({exc}); pass one of "
                             "`jepa-envs list`") from None

    def fields(self) -> dict:
        """What ``jepa_policy.lerobot_format.model_config`` reads."""
        return {"task": self.task, "n_obs_steps": self.n_obs_steps, **{n: getattr(self, n) for n in MODEL_FIELDS}}

    def given_features(self) -> dict[str, tuple[str, tuple[int, ...]]]:
        return {key: (ft.type.value, tuple(ft.shape)) for key, ft in
                {**(self.input_features or {}), **(self.output_features or {})}.items()}

    def model_config(self) -> tuple[TaskSpec, ModelConfig]:
        """The task spec at the features' image size and our ModelConfig (the features checked first)."""
        size = check_features(self.task_spec(), self.given_features())
        spec, cfg = model_config(self.fields(), size)
        return spec, cfg

    @property
    def has_future(self) -> bool:
        return self.arm not in ("mip", "diffusion")

    @property
    def observation_delta_indices(self) -> list[int]:
        """The history frames t-n_obs_steps+1 .. t and, for arms with a future token, the target frame t+k:
        LeRobot's loader clamps them at episode ends as our WindowDataset does."""
        history = list(range(1 - self.n_obs_steps, 1))
        return history + [self.future_k] if self.has_future else history

    @property
    def action_delta_indices(self) -> list[int]:
        """actions[t : t+H], the chunk decided at frame t (jepa_policy/dataset.py)."""
        return list(range(self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, betas=self.optimizer_betas, eps=self.optimizer_eps,
                           weight_decay=self.optimizer_weight_decay, grad_clip_norm=self.optimizer_grad_clip_norm)

    def get_scheduler_preset(self) -> CosineDecayWithWarmupSchedulerConfig:
        return CosineDecayWithWarmupSchedulerConfig(num_warmup_steps=self.scheduler_warmup_steps,
                                                    num_decay_steps=self.scheduler_decay_steps,
                                                    peak_lr=self.optimizer_lr, decay_lr=0.0)

    def validate_features(self) -> None:
        self.model_config()

