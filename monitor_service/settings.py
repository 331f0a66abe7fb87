"""Service configuration, read from the environment with the ``JEPA_MONITOR_`` prefix."""
from __future__ import annotations

import difflib
import math
import os
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class MonitorSettings(BaseSettings):
    """Every knob of the monitor; defaults equal the paper's protocol (Sec. 4.10) where it has one."""

    model_config = SettingsConfigDict(env_prefix="JEPA_MONITOR_", extra="forbid")

    database_url: str = Field("sqlite:///jepa_monitor.db", description="SQLAlchemy URL; SQLite (WAL) or PostgreSQL")
    admin_key: str | None = Field(None, description="bootstrap admin API key, upserted at start-up")
    max_body_bytes: int = Field(8 * 1024 * 1024, gt=0, description="larger request bodies get 413")
    # Paper Sec. 4.10: the early score is the median NMSE of the first five decisions.
    early_decisions: int = Field(5, ge=1)
    # The running statistic is the median of the most recent `running_window` values (Sec. 3.6 sliding window).
    # Window, debounce and clear ratio are part of every calibrated rule: change them and recalibrate.
    running_window: int = Field(5, ge=1)
    alpha: float = Field(0.1, ge=0.001, lt=1.0,
                         description="guaranteed rate of successful episodes that raise any alert (rules.py)")
    alert_rule: Literal["running", "band"] = Field(
        "band", description="alert rule of new calibrations: running median of NMSE, or NMSE judged against the "
        "successes' band at the same decision step (docs/monitor.md)")
    threshold_shape: Literal["flat", "running-max"] = Field(
        "flat", description="threshold shape of new calibrations over the decision index: flat (lambda of the length "
        "regimes still open), or running-max (plus the successes' median running maximum: lower early thresholds)")
    detection_folds: int = Field(5, ge=2, le=20, description="folds of the cross-fitted detection figures")
    n_bootstrap: int = Field(10_000, ge=100)
    n_permutation: int = Field(10_000, ge=100)
    stats_seed: int = 0
    alert_debounce: int = Field(2, ge=1, description="consecutive evaluations over threshold before raising")
    alert_clear_ratio: float = Field(0.8, gt=0.0, le=1.0, description="hysteresis: clear below ratio * threshold")
    webhook_urls: list[str] = Field(default_factory=list)
    webhook_max_attempts: int = Field(5, ge=1)
    webhook_backoff_s: float = Field(0.5, ge=0.0)
    webhook_timeout_s: float = Field(5.0, gt=0.0)
    live_episode_s: float = Field(300.0, gt=0.0, description="an episode without outcome is live this long")
    sse_poll_s: float = Field(0.5, gt=0.0)
    run_migrations: bool = True
    create_database: bool = Field(False, description="create a missing SQLite file (`jepa-monitor serve --create`); "
                                  "otherwise a database that `jepa-monitor db upgrade` did not make is refused")

    @field_validator("alpha", "alert_clear_ratio", "webhook_backoff_s", "webhook_timeout_s", "live_episode_s",
                     "sse_poll_s", mode="before")
    @classmethod
    def _finite(cls, value, info):
        """nan and inf fail the bounds with a misleading message ("Input should be less than 1"): say what is wrong."""
        try:
            number = float(value)
        except (TypeError, ValueError):
            return value   # pydantic's own message for what is not a number
        if math.isfinite(number):
            return value
        bounds = {"alpha": "in [0.001, 1)", "alert_clear_ratio": "in (0, 1]", "webhook_backoff_s": ">= 0"}
        raise ValueError(f"{info.field_name} must be a finite number {bounds.get(info.field_name, '> 0')}, "
                         f"got {value!r}")

    @field_validator("database_url")
    @classmethod
    def _known_backend(cls, url: str) -> str:
        if not (url.startswith("sqlite") or url.startswith("postgres")):
            raise ValueError(
                f"database_url starts with {url.split('://', 1)[0][:40]!r}, neither SQLite nor PostgreSQL; use "
                "sqlite:///path.db or postgresql+psycopg://user@host/db"
            )
        return url


PREFIX = "JEPA_MONITOR_"
# read by other parts than the settings: the supervisor of `serve --workers N`, the bench's floor app
OTHER_VARIABLES = {"JEPA_MONITOR_SUPERVISOR_PID", "JEPA_MONITOR_FLOOR_DB"}


def unknown_variables(environ=None) -> list[str]:
    """One warning per JEPA_MONITOR_* environment variable that no setting reads (a mistyped name is otherwise
    ignored silently), naming the closest setting."""
    environ = os.environ if environ is None else environ
    settings = sorted(name.upper() for name in MonitorSettings.model_fields)
    out = []
    for name in sorted(n for n in environ if n.upper().startswith(PREFIX)):
        if name.upper() in OTHER_VARIABLES or name.upper()[len(PREFIX):] in settings:
            continue
        close = _closest(name.upper()[len(PREFIX):], settings)
        out.append(f"{name} is not a setting of the monitor and is ignored; "
                   + (f"did you mean {PREFIX}{close}?" if close else
                      f"the settings are {', '.join(PREFIX + s for s in settings)}"))
    return out


def _closest(typed: str, names: list[str]) -> str | None:
    """The setting a mistyped name most likely meant: one whose letters it abbreviates in order with the same
    first letter (DB -> DATABASE_URL), else the closest spelling."""
    def abbreviates(name: str) -> bool:
        rest = iter(name)
        return bool(typed) and name[0] == typed[0] and all(c in rest for c in typed.replace("_", ""))
    short = sorted((n for n in names if abbreviates(n)), key=len)
    if short:
        return short[0]
    close = difflib.get_close_matches(typed, names, n=1, cutoff=0.5)
    return close[0] if close else None
