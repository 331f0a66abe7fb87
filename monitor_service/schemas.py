"""Pydantic models of every request and response body."""
from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import Path as FastApiPath
from pydantic import (AfterValidator, BaseModel, BeforeValidator, ConfigDict, Discriminator, Field, Tag, WithJsonSchema,
                      model_validator)

from monitor_service.scoring import SERVICE_SIGNALS

Name = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.:\-]+$")]
Role = Literal["robot", "operator", "admin"]
# Integers are bounded so every one fits the database's 32-bit INTEGER columns (PostgreSQL), step + horizon too.
MAX_ID = 2**31 - 1
MAX_STEP = 2**30          # episode steps: about 1.7 years at 20 Hz
MAX_HORIZON = 1_000_000
MAX_SEED = 2**32 - 1
# Input models are strict (no "5" for 5, no true for 1), as the JSON Schema they publish; an integral float
# such as 3.0 is a JSON Schema integer, so it is taken as one.
def _integral(v: Any) -> Any:
    return int(v) if isinstance(v, float) and v.is_integer() else v


def json_int(ge: int, le: int) -> Any:
    """A bounded JSON Schema integer (constraints first, so the published schema states them)."""
    return Annotated[int, Field(ge=ge, le=le), BeforeValidator(_integral)]
# Timestamps are stored as naive UTC; the API states the offset (RFC 3339 date-time).
UtcDatetime = Annotated[dt.datetime, AfterValidator(lambda v: v if v.tzinfo else v.replace(tzinfo=dt.timezone.utc))]


ObjectId = Annotated[int, FastApiPath(ge=1, le=MAX_ID, description="row id")]


class Error(BaseModel):
    """Every 4xx answer: one line naming the problem and the fix."""

    detail: str


ERROR_MEANING = {
    400: "malformed body or header",
    401: "no API key, or an unknown or revoked one",
    403: "the key's role or robot may not do this",
    404: "unknown task, episode, calibration, alert or key",
    409: "conflicts with what is stored",
    413: "body over the size limit",
    422: "a field is invalid, or the data cannot support the request",
}


def errors(*codes: int) -> dict:
    """``responses=`` of a route: the 4xx answers it gives besides those of auth and body parsing."""
    return {code: {"model": Error, "description": ERROR_MEANING[code]} for code in codes}


F32_MAX = float(np.finfo(np.float32).max)


def _to_latent(value: Any) -> np.ndarray:
    """Accept a JSON list or a decoded float32 array; demand a finite, non-empty 1-D vector."""
    if isinstance(value, np.ndarray):
        if value.dtype == np.float32 and value.ndim == 1 and value.size:   # msgpack's arrays: only check finite
            if not np.isfinite(value).all():
                raise ValueError(f"latent has NaN or inf at index {int(np.flatnonzero(~np.isfinite(value))[0])}; "
                                 "send finite values only")
            return value.astype("<f4", copy=False)
        arr = value
    elif isinstance(value, list):
        if not set(map(type, value)) <= {float, int}:   # at C speed: no bool, str, list or null among them
            raise ValueError("latent must be a list of numbers")
        try:
            arr = np.asarray(value, dtype=np.float64)
        except OverflowError:   # an integer beyond float64 (e.g. 400 digits)
            index = next(i for i, v in enumerate(value) if isinstance(v, int) and abs(v) > 3.4e38)
            raise ValueError(f"latent value at index {index} overflows float32; rescale the latent") from None
    else:
        raise ValueError(f"latent must be a list of numbers or a float32 array, got {type(value).__name__}")
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"latent must be a non-empty 1-D vector, got shape {list(arr.shape)}")
    finite = np.isfinite(arr)
    if not finite.all():
        raise ValueError(f"latent has NaN or inf at index {int(np.flatnonzero(~finite)[0])}; send finite values only")
    if np.abs(arr).max() > F32_MAX:
        raise ValueError("latent overflows float32; rescale the latent")
    return arr.astype("<f4")


Latent = Annotated[
    np.ndarray,
    BeforeValidator(_to_latent),
    WithJsonSchema({"type": "array", "items": {"type": "number", "minimum": -3.4e38, "maximum": 3.4e38},
                    "minItems": 1, "description": "float32 latent vector, finite, non-empty"}),
]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, strict=True)


MAX_SIGNALS = 32
RESERVED_SIGNALS = (*SERVICE_SIGNALS, "nmse_persistence")   # nmse, nmse_ratio and the persistence control
# (NMSE of z_now): computed by the service from the latents; a named score of one of these names would be shadowed
# by the service's own column in calibration (accepted, stored, then never calibrated)


def _check_scores(value: Any) -> Any:
    """Named per-decision scores: finite, non-negative (larger = riskier), not a reserved name."""
    if isinstance(value, dict):
        for name, v in value.items():
            if name in RESERVED_SIGNALS:
                raise ValueError(f"score {name!r} is computed by the service from "
                                 + {"nmse": "z_hat", "nmse_ratio": "z_hat, z_now"}.get(name, "z_now")
                                 + " and the realized latent; send "
                                 "the latents instead, or name your score differently")
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"score {name!r} must be a number, got {type(v).__name__}")
            if not np.isfinite(v):
                raise ValueError(f"score {name!r} is {v}; send finite scores only (leave a signal out of `scores` "
                                 "when this decision has none)")
            if v < 0:
                raise ValueError(f"score {name!r} is {v}; scores are non-negative risks, larger = riskier (shift or "
                                 "negate it on the robot's side)")
    return value


Scores = Annotated[
    dict[Name, float], BeforeValidator(_check_scores), Field(max_length=MAX_SIGNALS),
    WithJsonSchema({"type": "object", "maxProperties": MAX_SIGNALS,
                    "propertyNames": {"pattern": r"^[A-Za-z0-9_.:\-]+$", "minLength": 1, "maxLength": 128,
                                      "not": {"enum": list(RESERVED_SIGNALS)}},
                    "additionalProperties": {"type": "number", "minimum": 0, "maximum": 1.7e308}}),
]


class DecisionIn(_Strict):
    """One policy decision: the predicted future latent z_hat for step t + k (Sec. 3.6), and/or named
    per-decision scores of signals registered for the task."""

    # the model validator's rule, published: latents (z_hat with horizon), or scores alone
    model_config = ConfigDict(json_schema_extra={"anyOf": [
        {"required": ["z_hat", "horizon"], "properties": {"z_hat": {"type": "array"}, "horizon": {"type": "integer"}}},
        {"required": ["scores"], "properties": {"scores": {"type": "object", "minProperties": 1},
                                                "z_hat": {"type": "null"}, "horizon": {"type": "null"},
                                                "z_now": {"type": "null"}}}]})

    kind: Literal["decision"] = "decision"
    task: Name
    episode: Name
    step: json_int(0, MAX_STEP) = Field(description="decision step t")
    horizon: json_int(1, MAX_HORIZON) | None = Field(None, description="prediction horizon k (with z_hat)")
    z_hat: Latent | None = Field(None, description="predicted latent of step t + k; optional when scores are sent")
    scores: Scores | None = Field(
        None, description="named per-decision risk scores (non-negative, larger = riskier) of signals registered "
        "for the task, e.g. {\"stac\": 0.12}; calibrated and alerted on per signal")
    z_now: Latent | None = Field(
        None, description="the current latent z_t = E_rgb(o_t), optional: scores the persistence baseline "
        "z_hat = z_t against the same realized target (a control of the paper's Sec. 4.10)")
    robot: Name | None = Field(None, description="defaults to the robot of the API key")
    checkpoint: str | None = Field(None, max_length=256)
    held_out: bool = Field(False, description="a labelled calibration episode")
    group: Name | None = Field(None, description="held-out split group, e.g. the checkpoint's training seed")

    @model_validator(mode="after")
    def _latents_or_scores(self) -> "DecisionIn":
        if self.z_hat is None and not self.scores:
            raise ValueError("a decision carries z_hat (with horizon) or scores, or both")
        if (self.z_hat is None) != (self.horizon is None):
            raise ValueError("z_hat and horizon go together: the prediction of step t + horizon")
        if self.z_now is not None and self.z_hat is None:
            raise ValueError("z_now scores the persistence control against z_hat's target; send z_hat with it")
        return self


class TargetIn(_Strict):
    """The realized latent E_rgb(o_step) of an episode's step."""

    kind: Literal["target"] = "target"
    episode: Name
    step: json_int(0, MAX_STEP + MAX_HORIZON)
    z: Latent


class OutcomeIn(_Strict):
    """The episode's outcome; failure is the positive class of every statistic."""

    kind: Literal["outcome"] = "outcome"
    episode: Name
    success: bool
    held_out: bool | None = None
    group: Name | None = None
    length: json_int(1, MAX_STEP + MAX_HORIZON) | None = Field(None,
                               description="episode length in env steps (detection lead times)")


def _record_kind(value: Any) -> str | None:
    """A record's kind: its ``kind`` field, else what its fields say (z_hat: decision, z: target, success:
    outcome), as the single-record routes, where ``kind`` may be left out, read it."""
    if not isinstance(value, dict):
        return getattr(value, "kind", None)
    if "kind" in value:
        return value["kind"] if isinstance(value["kind"], str) else None
    return next((kind for key, kind in (("z_hat", "decision"), ("scores", "decision"), ("z", "target"),
                                        ("success", "outcome")) if key in value), None)


Record = Annotated[
    Annotated[DecisionIn, Tag("decision")] | Annotated[TargetIn, Tag("target")] | Annotated[OutcomeIn, Tag("outcome")],
    Discriminator(_record_kind, custom_error_type="record_kind",
                  custom_error_message="a record is a decision, target or outcome: set kind, or send its fields "
                                       "(z_hat, z or success)"),
]


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
    alert_state: dict[str, int | None] = Field(
        default_factory=dict, description="every episode this request touched -> the id of its open alert after "
                                          "the request, or null when none is open (a robot loop's alert state)")
    beyond_calibration: list[str] = Field(
        default_factory=list, description="episodes this request touched that have run beyond the longest "
                                          "calibrated episode: no false-alert guarantee covers their later decisions")


class TaskIn(_Strict):
    latent_dim: json_int(1, 1_000_000) | None = None
    description: str = Field("", max_length=512)
    signals: list[Name] | None = Field(None, max_length=MAX_SIGNALS, description="named per-decision scores robots "
                                       "may send (added to those registered; nmse needs no registration)")


class TaskOut(BaseModel):
    name: str
    latent_dim: int | None
    description: str
    signals: list[str] = Field(description="named scores robots may send beside (or instead of) the latents")
    created_at: UtcDatetime


class DecisionOut(BaseModel):
    step: int
    horizon: int | None
    target_step: int | None
    nmse: float | None
    nmse_persistence: float | None = Field(description="NMSE of z_t against the same target, when z_now was sent")
    nmse_ratio: float | None = Field(None, description="nmse / nmse_persistence, the service's nmse_ratio signal "
                                     "(null without z_now, before the target, or when the scene did not change)")
    scores: dict[str, float] | None = Field(description="the named scores sent with it")


class EpisodeOut(BaseModel):
    id: str
    task: str
    robot: str
    checkpoint: str | None
    group: str | None
    held_out: bool
    success: bool | None
    early_score: float | None = Field(description="median NMSE of the first five decisions of the episode's decision "
                                      "grid, published once all five are scored")
    early_revisions: int = Field(description="times a published early score changed or was withdrawn (a late "
                                             "decision moved the grid); 0: never revised")
    running_score: float | None = Field(description="median NMSE of the last running_window scored decisions")
    risk_score: float | None = Field(description="latest value of the calibrated alert rule's statistic")
    risk_threshold: float | None = Field(description="the threshold that value was judged against (it depends on "
                                                     "the decision index)")
    calibrated_decisions: int | None = Field(description="scored decisions of the longest calibrated episode")
    beyond_calibration: bool = Field(description="the episode has run beyond calibrated_decisions: no false-alert "
                                                 "guarantee covers its later decisions")
    gaps: int = Field(description="decision indices up to the latest decision with no decision received (lost, "
                                  "unsent, or still to arrive late), on the grid origin + k x cadence")
    gap_steps: list[int] = Field(description="the steps of those missing decisions (the first 50)")
    late_decisions: int = Field(description="decisions that arrived after a later decision of this episode")
    length: int | None = Field(description="episode length in env steps, from its outcome")
    n_decisions: int
    n_scored: int
    open_alert_id: int | None
    alert_note: str = Field(description="why this episode can or cannot raise alerts")
    live: bool
    started_at: UtcDatetime
    updated_at: UtcDatetime


class RiskPoint(BaseModel):
    step: int = Field(description="decision step t")
    known_at: int = Field(description="env step t + k at which its NMSE became known")
    value: float = Field(description="the alert rule's running statistic after this decision")
    threshold: float = Field(description="the threshold of this decision index")
    beyond_calibration: bool = Field(description="the index lies beyond the calibrated decisions")


class EpisodeDetail(EpisodeOut):
    decisions: list[DecisionOut]
    rule: str | None = Field(description="the active calibration's alert rule (null: no usable calibration)")
    detector: str | None = Field(description="which signals alert and how, e.g. 'fiper(stac+nmse) band'")
    threshold: float | None = Field(description="its first signal's threshold at the longest calibrated decision "
                                                "index; each risk point carries its own")
    risk: list[RiskPoint] = Field(description="the first signal's rule statistic over the episode (the dashboard's "
                                              "trajectory)")
    signal_risk: dict[str, list[RiskPoint]] = Field(description="every alerting signal's rule statistic")


class CalibrateIn(_Strict):
    task: Name
    checkpoint: str | None = None
    alpha: float | None = Field(None, ge=0.001, lt=1.0,
                                description="guaranteed false-alert rate per successful episode (0.001 needs 999 "
                                "successes)")
    rule: Literal["running", "band"] | None = Field(
        None, description="the alert rule to calibrate (default: the service's alert_rule); window, debounce and "
        "hysteresis are the service's settings and become part of the calibration")
    signals: list[Name] | None = Field(None, min_length=1, max_length=MAX_SIGNALS, description="the signals that "
                                       "alert (default [\"nmse\"]): nmse and/or scores registered for the task")
    combination: Literal["single", "fiper", "bonferroni"] | None = Field(
        None, description="how several signals alert: fiper (two signals over at one decision) or bonferroni (any "
        "of K, each at alpha / K); default single for one signal, bonferroni for several")
    shape: Literal["flat", "running-max"] | None = Field(
        None, description="the threshold's shape over the decision index (default: the service's threshold_shape; "
        "docs/monitor.md)")
    folds: json_int(2, 20) | None = Field(None, description="folds of the cross-fitted detection figures")
    n_bootstrap: json_int(100, 200_000) | None = None
    n_permutation: json_int(100, 200_000) | None = None
    seed: json_int(0, MAX_SEED) | None = None


class CalibrationOut(BaseModel):
    id: int
    task: str
    checkpoint: str | None
    active: bool
    rule: str = Field(description="the calibrated alert rule: running or band (monitor_service/rules.py)")
    threshold: float | None = Field(description="alarm threshold of the rule's statistic")
    auroc: float
    result: dict
    created_at: UtcDatetime


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
    state: Literal["open", "acknowledged", "cleared", "resolved"] = Field(
        description="open: raised, nobody took it; acknowledged: an operator took it; cleared: the statistic fell "
                    "back below the hysteresis level while the episode ran; resolved: the episode's outcome arrived")
    acknowledged_by: str | None
    acknowledged_at: UtcDatetime | None
    note: str
    raised_at: UtcDatetime
    cleared_at: UtcDatetime | None
    resolved_at: UtcDatetime | None
    resolution: Literal["failure", "success"] | None = Field(
        description="the outcome that resolved it: failure (a true alert) or success (a false alert)")
    beyond_calibration: bool = Field(description="raised beyond the calibrated decisions (no guarantee there)")
    signals: str = Field(description="the signal(s) whose calibrated rule raised it, comma-separated")
    no_promise: bool = Field(False, description="the episode could still end at a length whose false-alert rate "
                                                "the calibration does not promise (too few held-out successes that "
                                                "long); the note names the lengths and counts")


class AckIn(_Strict):
    note: str = Field("", max_length=512)


class RobotKeyIn(_Strict):
    """A robot key: it ingests for exactly one robot and reads nothing."""

    name: Name
    role: Literal["robot"]
    robot: Name = Field(description="the robot this key may write for")


class OperatorKeyIn(_Strict):
    """An operator key: reads and acknowledges alerts; never ingests."""

    name: Name
    role: Literal["operator"]
    robot: None = Field(None, description="only robot keys name a robot")


class AdminKeyIn(OperatorKeyIn):
    """An admin key: registers tasks, manages keys, calibrates, reads; never ingests."""

    role: Literal["admin"]


# one model per role, so the published discriminator maps each role to exactly one schema
KeyIn = Annotated[RobotKeyIn | OperatorKeyIn | AdminKeyIn, Field(discriminator="role")]


class KeyOut(BaseModel):
    id: int
    name: str
    role: str
    robot: str | None
    created_at: UtcDatetime
    revoked_at: UtcDatetime | None


class KeyCreated(KeyOut):
    key: str = Field(description="the secret; shown once, store it now")


class Health(BaseModel):
    status: str
    detail: str = ""

