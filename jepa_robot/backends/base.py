"""The interface every hardware backend of the bridge implements.

The bridge owns timing, safety and episodes; a backend only moves the robot and reads its sensors. All
methods but ``emergency_stop`` are called from the bridge's single event-loop thread; ``emergency_stop`` comes
from the e-stop thread at any moment, also while another call runs, and must stop the robot without waiting for
that call.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from jepa_envs.tasks.spec import ABS_ACTION_DIM_PER_ARM, TaskSpec


class BackendUnavailable(ImportError):
    """A backend's hardware SDK is not installed; the message says what to install."""


@dataclass
class StepResult:
    """What one executed control step returns; ``obs`` None: the bridge observes at the end of the period."""

    obs: dict[str, np.ndarray] | None
    reward: float = 0.0
    terminated: bool = False
    truncated: bool = False
    info: dict = field(default_factory=dict)


class RobotBackend(ABC):
    """A robot the bridge can drive with absolute actions at ``task_spec.control_hz``."""

    task_spec: TaskSpec
    #: "sim": success comes from the simulator; "operator": the operator confirms it at episode end
    success_source: str = "operator"
    #: whether the bridge must pace actions in wall-clock time (real hardware) or may run them back to back
    realtime: bool = True

    @property
    @abstractmethod
    def action_low(self) -> np.ndarray: ...

    @property
    @abstractmethod
    def action_high(self) -> np.ndarray: ...

    @property
    def rotation6d_starts(self) -> list[int]:
        """Indices where 6-D rotation blocks start in the action (checked for degeneracy): absolute robot
        actions are [position 3, 6-D rotation 6, gripper 1] per arm (Sec. 4.1); a task without arms (PushT)
        has none."""
        return [ABS_ACTION_DIM_PER_ARM * arm + 3 for arm in range(self.task_spec.num_arms)]

    @abstractmethod
    def reset(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
        """Start an episode from the home configuration; returns the first observation and info."""

    @abstractmethod
    def apply(self, action: np.ndarray) -> StepResult:
        """Command one absolute action.

        Simulators step and return the resulting observation. Real-time backends return at once with
        ``obs=None``; the bridge waits out the control period (serving e-stop and heartbeats) and then calls
        ``observe``.
        """

    @abstractmethod
    def hold(self) -> None:
        """Stop where the robot is now (watchdog, lost link, e-stop, refused action)."""

    def emergency_stop(self) -> None:
        """Stop now, from the e-stop thread, concurrently with any other call (see the module docstring). The
        default is ``hold``: right for backends whose hold touches no state another call is changing (the
        simulators, whose hold moves nothing); hardware overrides it with its driver's thread-safe stop."""
        self.hold()

    @abstractmethod
    def home(self) -> None:
        """Drive to the home configuration (explicit operator or reset request only)."""

    @abstractmethod
    def observe(self) -> dict[str, np.ndarray]:
        """The current observation without moving."""

    def current_action(self) -> np.ndarray | None:
        """The absolute action that matches the current pose (jump-limit reference), None if unknown."""
        return None

    def joint_positions(self) -> np.ndarray | None:
        """Measured joint positions of all arms, None for backends without joints."""
        return None

    @property
    def joint_count(self) -> int | None:
        """How many joints ``joint_positions`` reports (the length joint limits must have), None: no joints."""
        return None

    def set_render_images(self, enabled: bool) -> None:
        """Skip (False) or produce (True) camera images on the following steps."""

    def close(self) -> None:
        """Release the hardware or simulator."""
