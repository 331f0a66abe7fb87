"""Pydantic models of every request and response body."""
from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, WithJsonSchema

Name = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.:\-]+$")]
Role = Literal["robot", "operator", "admin"]


def _to_latent(value: Any) -> np.ndarray:
    """Accept a JSON list or a decoded float32 array; demand a finite, non-empty 1-D vector."""
    if isinstance(value, np.ndarray):
        arr = value
    elif isinstance(value, list):
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise ValueError("latent must be a list of numbers")
        arr = np.asarray(value, dtype=np.float64)
    else:
        raise ValueError(f"latent must be a list of numbers or a float32 array, got {type(value).__name__}")
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"latent must be a non-empty 1-D vector, got shape {list(arr.shape)}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(f"latent has NaN or inf at index {int(bad[0])}; send finite values only")
    arr32 = arr.astype("<f4")
    if not np.all(np.isfinite(arr32)):
        raise ValueError("latent overflows float32; rescale the latent")
    return arr32


Latent = Annotated[
    np.ndarray,
    BeforeValidator(_to_latent),
    WithJsonSchema({"type": "array", "items": {"type": "number"}, "description": "float32 latent vector"}),
]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True)


class DecisionIn(_Strict):
    """One policy decision: the predicted future latent z_hat for step t + k (Sec. 3.6)."""

    kind: Literal["decision"] = "decision"
    task: Name
    episode: Name
    step: int = Field(ge=0, description="decision step t")
    horizon: int = Field(ge=1, description="prediction horizon k")
    z_hat: Latent
    z_now: Latent | None = Field(
        None, description="the current latent z_t = E_rgb(o_t), optional: scores the persistence baseline "
        "z_hat = z_t against the same realized target (a control of the paper's Sec. 4.10)")
    robot: Name | None = Field(None, description="defaults to the robot of the API key")
    checkpoint: str | None = Field(None, max_length=256)
    held_out: bool = Field(False, description="a labelled calibration episode")
    group: Name | None = Field(None, description="held-out split group, e.g. the checkpoint's training seed")


class TargetIn(_Strict):
    """The realized latent E_rgb(o_step) of an episode's step."""

    kind: Literal["target"] = "target"
    episode: Name
    step: int = Field(ge=0)
    z: Latent


class OutcomeIn(_Strict):
    """The episode's outcome; failure is the positive class of every statistic."""

    kind: Literal["outcome"] = "outcome"
    episode: Name
    success: bool
    held_out: bool | None = None
    group: Name | None = None
    length: int | None = Field(None, ge=1, description="episode length in env steps (detection lead times)")


Record = Annotated[DecisionIn | TargetIn | OutcomeIn, Field(discriminator="kind")]


class BatchIn(_Strict):
    """Records applied in order in one transaction: all are committed or none."""

    records: list[Record] = Field(min_length=1, max_length=10_000)


class IngestResult(BaseModel):
    accepted: int
    decisions: int = 0
    targets: int = 0
    outcomes: int = 0
    scored: int = Field(0, description="decisions that received their NMSE in this request")
    alerts_raised: list[int] = Field(default_factory=list)


class TaskIn(_Strict):
    latent_dim: int | None = Field(None, ge=1, le=1_000_000)
    description: str = Field("", max_length=512)


class TaskOut(BaseModel):
    name: str
    latent_dim: int | None
    description: str
    created_at: dt.datetime


class DecisionOut(BaseModel):
    step: int
    horizon: int
    target_step: int
    nmse: float | None
    nmse_persistence: float | None = Field(description="NMSE of z_t against the same target, when z_now was sent")


class EpisodeOut(BaseModel):
    id: str
    task: str
    robot: str
    checkpoint: str | None
    group: str | None
    held_out: bool
    success: bool | None
    early_score: float | None
    running_score: float | None = Field(description="median NMSE of the last running_window scored decisions")
    risk_score: float | None = Field(description="latest value of the calibrated alert rule's statistic")
    length: int | None = Field(description="episode length in env steps, from its outcome")
    n_decisions: int
    n_scored: int
    open_alert_id: int | None
    alert_note: str = Field(description="why this episode can or cannot raise alerts")
    live: bool
    started_at: dt.datetime
    updated_at: dt.datetime


class RiskPoint(BaseModel):
    step: int = Field(description="decision step t")
    known_at: int = Field(description="env step t + k at which its NMSE became known")
    value: float = Field(description="the alert rule's running statistic after this decision")


class EpisodeDetail(EpisodeOut):
    decisions: list[DecisionOut]
    rule: str | None = Field(description="the active calibration's alert rule (null: no usable calibration)")
    threshold: float | None = Field(description="its threshold; an alert needs `debounce` values above it")
    risk: list[RiskPoint] = Field(description="the rule's statistic over the episode (the dashboard's trajectory)")


class CalibrateIn(_Strict):
    task: Name
    checkpoint: str | None = None
    alpha: float | None = Field(None, gt=0.0, lt=1.0, description="guaranteed false-alert rate per successful episode")
    rule: Literal["running", "band"] | None = Field(
        None, description="the alert rule to calibrate (default: the service's alert_rule); window, debounce and "
        "hysteresis are the service's settings and become part of the calibration")
    folds: int | None = Field(None, ge=2, le=20, description="folds of the cross-fitted detection figures")
    n_bootstrap: int | None = Field(None, ge=100, le=200_000)
    n_permutation: int | None = Field(None, ge=100, le=200_000)
    seed: int | None = None


class CalibrationOut(BaseModel):
    id: int
    task: str
    checkpoint: str | None
    active: bool
    rule: str = Field(description="the calibrated alert rule: running or band (monitor_service/rules.py)")
    threshold: float | None = Field(description="alarm threshold of the rule's statistic")
    auroc: float
    result: dict
    created_at: dt.datetime


class PooledWarning(BaseModel):
    warning: str
    auroc: float | None
    n_episodes: int


class ReportOut(BaseModel):
    tasks: list[CalibrationOut]
    uncalibrated_tasks: list[str]
    pooled: PooledWarning


class AlertOut(BaseModel):
    id: int
    episode_id: str
    task: str
    robot: str
    step: int
    score: float
    threshold: float
    calibration_id: int
    state: str
    acknowledged_by: str | None
    acknowledged_at: dt.datetime | None
    note: str
    raised_at: dt.datetime
    cleared_at: dt.datetime | None


class AckIn(_Strict):
    note: str = Field("", max_length=512)


class KeyIn(_Strict):
    name: Name
    role: Role
    robot: Name | None = Field(None, description="required for robot keys: the robot this key may write for")


class KeyOut(BaseModel):
    id: int
    name: str
    role: str
    robot: str | None
    created_at: dt.datetime
    revoked_at: dt.datetime | None


class KeyCreated(KeyOut):
    key: str = Field(description="the secret; shown once, store it now")


class Health(BaseModel):
    status: str
    detail: str = ""

