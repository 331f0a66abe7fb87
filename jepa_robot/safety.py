"""Safety rules the bridge applies to every action, whatever the client sends.

Pure functions and one small guard class, so each rule can be tested without a bridge: finite and
well-shaped actions (else refused outright), workspace and gripper bounds on the absolute action, a per-step
jump limit against the previously commanded action, joint limits on the measured joint positions after every
driver step (the ARX-5 SDK solves IK inside its controller, so joints are checked where they are known), and
the timing rules (watchdog deadline, link timeout) that the bridge's event loop enforces.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator


class InvalidAction(ValueError):
    """An action that can never be executed (NaN, infinite, wrong shape, degenerate rotation)."""


# beyond these a rule is switched off in all but name: a watchdog that waits an hour is no watchdog
MAX_COMMAND_DEADLINE_S = 600.0
MAX_LINK_SECONDS = 600.0
# ... and below these the bridge cannot keep them: pings every microsecond wedge its loop
MIN_HEARTBEAT_S = 0.001
MIN_LINK_TIMEOUT_S = 0.005
MIN_COMMAND_DEADLINE_S = 0.01
_NUMBER_FIELDS = ("action_low", "action_high", "max_step_delta", "joint_low", "joint_high", "command_deadline_s",
                  "link_timeout_s", "heartbeat_interval_s", "link_grace_s")


def refuse_non_numbers(v):
    """A number field takes numbers (or lists of them) only: TOML ``true`` is not 1.0 and ``"inf"`` is not a
    number (pydantic's lax mode would convert both)."""
    for item in (v if isinstance(v, list) else [v]):
        if item is not None and (isinstance(item, bool) or not isinstance(item, (int, float))):
            raise ValueError(f"must be a number, not {type(item).__name__} {item!r:.30}")
    return v


class SafetyConfig(BaseModel):
    """Limits of one robot set-up; the bridge refuses to start with an inconsistent one.

    Every number must be finite (a NaN compares false with everything, so ``jump > nan`` never fires and a NaN
    limit would switch its rule off): pydantic refuses NaN and infinity in every field, nested lists included.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    action_low: list[float] | None = None   # workspace / gripper lower bound per action dim (None: backend's)
    action_high: list[float] | None = None
    max_step_delta: list[float] | float | None = None  # per-step jump limit per action dim (None: off)
    on_violation: Literal["refuse", "clip"] = "refuse"
    rotation6d_starts: list[int] = []  # index of each 6-D rotation block (its two 3-vectors must not degenerate)
    joint_low: list[float] | None = None  # per joint of all arms, checked on measured joint positions
    joint_high: list[float] | None = None
    command_deadline_s: float = 2.0       # watchdog: longest silence between commands inside an episode
    link_timeout_s: float | None = None   # a silent connection is closed after this: default one control period
    heartbeat_interval_s: float | None = None  # the bridge's link pings: default a quarter of the above
    link_grace_s: float = 5.0             # a lost link holds the robot; control is released after this long

    @field_validator(*_NUMBER_FIELDS, mode="before")
    @classmethod
    def _numbers_only(cls, v):
        return refuse_non_numbers(v)

    @field_validator("command_deadline_s")
    @classmethod
    def _watchdog_on(cls, v: float) -> float:
        if not 0 < v <= MAX_COMMAND_DEADLINE_S:
            raise ValueError(f"must be > 0 and at most {MAX_COMMAND_DEADLINE_S:g} seconds (the command watchdog "
                             "cannot be switched off)")
        if v < MIN_COMMAND_DEADLINE_S:
            raise ValueError(f"must be at least {MIN_COMMAND_DEADLINE_S:g} seconds (and one control period): a "
                             "shorter watchdog interrupts every episode before its first action")
        return v

    @field_validator("link_grace_s")
    @classmethod
    def _grace_bounded(cls, v: float) -> float:
        if not 0 < v <= MAX_LINK_SECONDS:
            raise ValueError(f"must be > 0 and at most {MAX_LINK_SECONDS:g} seconds")
        return v

    @field_validator("link_timeout_s", "heartbeat_interval_s")
    @classmethod
    def _positive_or_default(cls, v: float | None) -> float | None:
        if v is not None and not 0 < v <= MAX_LINK_SECONDS:
            raise ValueError(f"must be > 0 and at most {MAX_LINK_SECONDS:g} seconds (or left out for the default)")
        return v

    @field_validator("heartbeat_interval_s")
    @classmethod
    def _heartbeat_floor(cls, v: float | None) -> float | None:
        if v is not None and v < MIN_HEARTBEAT_S:
            raise ValueError(f"must be at least {MIN_HEARTBEAT_S:g} seconds: faster pings would keep the bridge's "
                             "loop from anything else")
        return v

    @field_validator("link_timeout_s")
    @classmethod
    def _link_timeout_floor(cls, v: float | None) -> float | None:
        if v is not None and v < MIN_LINK_TIMEOUT_S:
            raise ValueError(f"must be at least {MIN_LINK_TIMEOUT_S:g} seconds: a shorter one holds a live link "
                             "between two of its echoes")
        return v

    def problems(self, action_dim: int, n_joints: int | None, control_hz: float | None = None,
                 action_range: tuple[np.ndarray, np.ndarray] | None = None,
                 joint_range: tuple[float, float] | None = None) -> list[str]:
        """Every length or bound that does not fit a robot with ``action_dim`` actions and ``n_joints`` joints,
        every workspace bound outside the backend's own ``action_range`` (when given), a jump limit as wide as the
        action range (it could never fire), joint limits outside the backend's ``joint_range`` (when given), and
        every timing rule that contradicts another at ``control_hz`` (when given).

        ``n_joints`` None: the backend measures no joints (PushT), so joint limits must be absent. Checked by
        the bridge before it opens any socket and by ``jepa-robot-bridge check`` before any hardware is touched.
        """
        out: list[str] = []

        def length(name: str, value, want: int, unit: str) -> None:
            if value is not None and len(value) != want:
                out.append(f"safety.{name} has {len(value)} entries; this task needs {want} (one per {unit})")

        length("action_low", self.action_low, action_dim, "action dimension")
        length("action_high", self.action_high, action_dim, "action dimension")
        if isinstance(self.max_step_delta, list):
            length("max_step_delta", self.max_step_delta, action_dim, "action dimension, or one number for all")
        delta = self.max_step_delta
        if delta is not None and any(d <= 0 for d in (delta if isinstance(delta, list) else [delta])):
            out.append("safety.max_step_delta must be > 0 in every dimension")
        for name, value in (("action_low", self.action_low), ("action_high", self.action_high),
                            ("joint_low", self.joint_low), ("joint_high", self.joint_high),
                            ("max_step_delta", delta if isinstance(delta, list) else None)):
            if value is not None and not all(np.isfinite(value)):
                out.append(f"safety.{name} has NaN or infinite entries")
        if action_range is not None:
            for name, value, inside in (("action_low", self.action_low, lambda v, lo, hi: v >= lo),
                                        ("action_high", self.action_high, lambda v, lo, hi: v <= hi)):
                if value is None or len(value) != action_dim:
                    continue
                outside = [i for i, (v, lo, hi) in enumerate(zip(value, *action_range)) if not inside(v, lo, hi)]
                if outside:
                    i = outside[0]
                    out.append(f"safety.{name} leaves the backend's own action range at indices {outside} (e.g. "
                               f"{value[i]:g} outside [{action_range[0][i]:g}, {action_range[1][i]:g}]); a "
                               "configured bound may only narrow it")
        if action_range is not None and delta is not None and np.all(np.isfinite(delta)):
            low = np.asarray(self.action_low if self.action_low is not None and len(self.action_low) == action_dim
                             else action_range[0], np.float64)
            high = np.asarray(self.action_high if self.action_high is not None and len(self.action_high) == action_dim
                              else action_range[1], np.float64)
            width = high - low
            limit = np.broadcast_to(np.asarray(delta, np.float64), width.shape) if not isinstance(delta, list) or len(
                delta) == action_dim else None
            wide = [] if limit is None else np.flatnonzero(limit >= width).tolist()
            if wide:
                i = wide[0]
                out.append(f"safety.max_step_delta is at or beyond the action range's width at indices {wide} (e.g. "
                           f"{limit[i]:g} >= {width[i]:g}): such a jump limit never fires; set a real limit or "
                           "leave max_step_delta out (check then says no jump limit is set)")
        if joint_range is not None and n_joints is not None:
            for name, value in (("joint_low", self.joint_low), ("joint_high", self.joint_high)):
                outside = [] if value is None else [i for i, v in enumerate(value)
                                                    if not joint_range[0] <= v <= joint_range[1]]
                if outside:
                    out.append(f"safety.{name} leaves the robot's joint range [{joint_range[0]:g}, {joint_range[1]:g}]"
                               f" rad at joints {outside} (e.g. {value[outside[0]]:g}): such a limit never fires")
        if self.action_low is not None and self.action_high is not None and len(self.action_low) == len(
                self.action_high) and any(lo > hi for lo, hi in zip(self.action_low, self.action_high)):
            out.append("safety.action_low must be <= action_high in every dimension")
        if n_joints is None:
            if self.joint_low is not None or self.joint_high is not None:
                out.append("safety.joint_low/joint_high are set but this robot reports no joints; remove them")
        else:
            length("joint_low", self.joint_low, n_joints, "joint of all arms")
            length("joint_high", self.joint_high, n_joints, "joint of all arms")
            if self.joint_low is not None and self.joint_high is not None and len(self.joint_low) == len(
                    self.joint_high) and any(lo >= hi for lo, hi in zip(self.joint_low, self.joint_high)):
                out.append("safety.joint_low must be below joint_high for every joint")
        for rot in self.rotation6d_starts:
            if not 0 <= rot <= action_dim - 6:
                out.append(f"safety.rotation6d_starts entry {rot} leaves no room for 6 rotation numbers "
                           f"in a {action_dim}-D action")
        if self.heartbeat_interval_s and self.link_timeout_s and 2 * self.heartbeat_interval_s > self.link_timeout_s:
            out.append("safety.heartbeat_interval_s must be at most half of link_timeout_s (several heartbeats per "
                       "timeout)")
        if control_hz is not None and self.heartbeat_interval_s and not self.link_timeout_s and (
                2 * self.heartbeat_interval_s > self.resolved_link_timeout(control_hz)):
            out.append(f"safety.heartbeat_interval_s ({self.heartbeat_interval_s:g}s) must be at most half the link "
                       f"timeout ({self.resolved_link_timeout(control_hz):g}s, one control period by default)")
        if control_hz is not None:
            # one rule (docs/real_robot.md, "Lost link and the command watchdog"): a link that goes silent is
            # held for link_grace_s; the watchdog only judges a live link, so it must not fire before a silent
            # link is even detected
            link_timeout = self.resolved_link_timeout(control_hz)
            if link_timeout >= self.command_deadline_s:
                out.append(f"safety.link_timeout_s ({link_timeout:g}s) must be below command_deadline_s "
                           f"({self.command_deadline_s:g}s): a silent link would trip the command watchdog before "
                           "it is detected as lost, and link_grace_s could never apply")
            elif self.command_deadline_s < 1.0 / control_hz:
                out.append(f"safety.command_deadline_s ({self.command_deadline_s:g}s) must be at least one control "
                           f"period ({1.0 / control_hz:g}s): the watchdog would fire between two actions")
        return out

    def resolved_link_timeout(self, control_hz: float) -> float:
        return float(self.link_timeout_s) if self.link_timeout_s else 1.0 / float(control_hz)

    def resolved_heartbeat(self, control_hz: float) -> float:
        if self.heartbeat_interval_s:
            return float(self.heartbeat_interval_s)
        return self.resolved_link_timeout(control_hz) / 4.0


def config_errors(exc: ValidationError, prefix: str = "safety.") -> list[str]:
    """One line per refused field of a pydantic ValidationError, naming the field, why and the value given. A
    field typed ``list | float`` gets one error per alternative from pydantic; here it gets one line (the
    finite-number reason first), and a list's entries are reported under the list's name."""
    by_field: dict[str, list[dict]] = {}
    for error in exc.errors():
        path = [str(p) for p in error["loc"] if isinstance(p, str) and "[" not in p and p not in _TYPE_TAGS]
        by_field.setdefault(".".join(path) or "config", []).append(error)
    lines = []
    for name, errors in by_field.items():
        error = next((e for e in errors if "finite" in e["msg"]), errors[0])
        reason = error["msg"].removeprefix("Value error, ")
        if "finite" in reason:
            reason += " (a NaN or infinite limit would switch its rule off)"
        given = error.get("input")
        if "\n" in reason:   # a model-level check with several problems, each naming its field
            lines += reason.splitlines()
            continue
        lines.append(f"{prefix}{name}: {reason}" + ("" if isinstance(given, dict) else f" (got {given!r:.60})"))
    if len(lines) > MAX_ERROR_LINES:   # thousands of unknown keys: a bounded answer, not one line each
        lines = lines[:MAX_ERROR_LINES] + [f"... and {len(lines) - MAX_ERROR_LINES} more problems of the same "
                                           "config (fix the ones above first)"]
    return lines


MAX_ERROR_LINES = 10   # lines of config_errors shown; the rest are counted in one line


_TYPE_TAGS = {"float", "int", "str", "bool", "list", "none", "function-after", "function-before"}


@dataclass
class Verdict:
    """Outcome of checking one action: what to execute (None when refused) and why."""

    action: np.ndarray | None
    violations: list[str] = field(default_factory=list)
    clipped: bool = False

    @property
    def refused(self) -> bool:
        return self.action is None

    def report(self) -> dict:
        return {"refused": self.refused, "clipped": self.clipped, "violations": list(self.violations)}


def _as_array(value, what: str) -> np.ndarray:
    try:
        return np.asarray(value)
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:   # ragged or mixed nested lists
        raise InvalidAction(f"{what} is not a numeric array ({type(exc).__name__})") from None


def validate_action(action, dim: int, rotation6d_starts: list[int] = ()) -> np.ndarray:
    """Return ``action`` as float64 (dim,) or raise InvalidAction naming what is wrong with it."""
    arr = _as_array(action, "action")
    if arr.dtype.kind not in "fiu":
        raise InvalidAction(f"action must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if arr.shape != (dim,):
        raise InvalidAction(f"action has shape {arr.shape}, this task needs ({dim},); send one absolute action")
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.isfinite(arr)).tolist()
        raise InvalidAction(f"action has NaN or infinite entries at indices {bad}; the policy output is broken")
    for start in rotation6d_starts:
        a, b = arr[start:start + 3], arr[start + 3:start + 6]
        if np.linalg.norm(a) < 1e-3 or np.linalg.norm(b) < 1e-3 or np.linalg.norm(np.cross(a, b)) < 1e-3:
            raise InvalidAction(f"6-D rotation at index {start} is degenerate (zero or parallel columns)")
    return arr


def validate_chunk(actions, dim: int, rotation6d_starts: list[int] = (), max_actions: int | None = None) -> np.ndarray:
    """Validate a whole (N, dim) chunk, 1 <= N <= ``max_actions``, before any of it moves the robot.

    A bad entry is named by its row (the action's place in the chunk) and its column (the action dimension).
    """
    arr = _as_array(actions, "action chunk")
    if arr.ndim != 2 or arr.shape[1] != dim or arr.shape[0] < 1:
        raise InvalidAction(f"action chunk has shape {arr.shape}, this task needs (N, {dim}) with N >= 1")
    if max_actions is not None and arr.shape[0] > max_actions:
        raise InvalidAction(f"action chunk has {arr.shape[0]} actions; this task executes at most {max_actions} per "
                            f"chunk, which is what its budget counts: send the first {max_actions} of the "
                            "predicted chunk")
    if arr.dtype.kind not in "fiu":
        raise InvalidAction(f"action chunk must be numeric, got dtype {arr.dtype}")
    finite = np.isfinite(arr.astype(np.float64))
    if not finite.all():
        rows, cols = np.nonzero(~finite)
        where = ", ".join(f"row {r} column {c}" for r, c in zip(rows[:8].tolist(), cols[:8].tolist()))
        raise InvalidAction(f"action chunk has NaN or infinite entries at {where}"
                            f"{' ...' if rows.size > 8 else ''}; the policy output is broken")
    out = []
    for row, action in enumerate(arr):
        try:
            out.append(validate_action(action, dim, rotation6d_starts))
        except InvalidAction as exc:
            raise InvalidAction(f"row {row} of the chunk: {exc}") from None
    return np.stack(out)


class ActionGuard:
    """Applies bounds, jump and joint limits to one validated action (Sec. 4.8 safety checks)."""

    def __init__(self, config: SafetyConfig, low: np.ndarray, high: np.ndarray):
        self.config = config
        dim = len(low)
        self.low = np.asarray(config.action_low if config.action_low is not None else low, dtype=np.float64)
        self.high = np.asarray(config.action_high if config.action_high is not None else high, dtype=np.float64)
        if self.low.shape != (dim,) or self.high.shape != (dim,):
            raise ValueError(f"safety action_low/action_high need {dim} entries each (the task's action size)")
        if np.any(self.low > self.high):
            raise ValueError("safety action_low must be <= action_high in every dimension")
        delta = config.max_step_delta
        self.max_delta = None if delta is None else np.broadcast_to(np.asarray(delta, np.float64), (dim,)).copy()
        if self.max_delta is not None and np.any(self.max_delta <= 0):
            raise ValueError("safety max_step_delta must be > 0 in every dimension")
        self.joint_low = None if config.joint_low is None else np.asarray(config.joint_low, np.float64)
        self.joint_high = None if config.joint_high is None else np.asarray(config.joint_high, np.float64)

    def check(self, action: np.ndarray, previous: np.ndarray | None) -> Verdict:
        """Check a validated action against the previously executed one; clip or refuse by configuration."""
        violations: list[str] = []
        out_low, out_high = action < self.low, action > self.high
        if np.any(out_low | out_high):
            idx = np.flatnonzero(out_low | out_high).tolist()
            violations.append(f"workspace/gripper bounds exceeded at action indices {idx}")
        if self.max_delta is not None and previous is not None:
            jump = np.abs(action - previous)
            if np.any(jump > self.max_delta):
                idx = np.flatnonzero(jump > self.max_delta).tolist()
                violations.append(f"per-step jump {jump[idx].round(4).tolist()} above limit at indices {idx}")
        if not violations:
            executed = action
        elif self.config.on_violation == "refuse":
            return Verdict(None, violations)
        else:
            executed = action.copy()
            if self.max_delta is not None and previous is not None:
                executed = np.clip(executed, previous - self.max_delta, previous + self.max_delta)
            executed = np.clip(executed, self.low, self.high)
        return Verdict(executed, violations, clipped=bool(violations))

    def joint_violation(self, q: np.ndarray | None) -> str | None:
        """Check measured joint positions (None: the backend has no joints) against the configured limits."""
        if q is None or (self.joint_low is None and self.joint_high is None):
            return None
        return joint_limit_violation(np.asarray(q, np.float64), self.joint_low, self.joint_high)


def joint_limit_violation(q: np.ndarray, low: np.ndarray | None, high: np.ndarray | None) -> str | None:
    """Name the joints of ``q`` outside [low, high], or None when all are inside."""
    bad = np.zeros(q.shape, dtype=bool)
    if low is not None:
        bad |= q < low
    if high is not None:
        bad |= q > high
    if np.any(bad):
        return f"joint limits exceeded at joints {np.flatnonzero(bad).tolist()} (q={q[bad].round(3).tolist()})"
    return None
