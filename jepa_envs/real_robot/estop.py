"""The e-stop latch: pressed from any thread, it stops the robot at once and outlives the bridge's process.

``press`` sets the latch and calls the backend's ``emergency_stop`` in the caller's thread (the operator
thread), without waiting for the event loop, the control socket or any other operator request. The event loop
checks the latch before it decides each action, so nothing decided after the press moves the robot; an action
decided just before it is followed by a hold as soon as its call returns (``bridge._execute``). The loop then
interrupts the episode (``RobotBridge._apply_estop_if_latched``).

With a ``state_file`` the latch survives the process: a bridge started after one that did not stop cleanly
(a crash, a kill, a power cut: its state still says ``running``) starts latched, as does one started after an
e-stop nobody cleared. Only an operator's ``clear`` releases it.
"""
from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)


class EStop:
    """The latch, the robot stop it triggers, and its record on disk."""

    def __init__(self, stop_robot: Callable[[], None], state_file: str | None = None):
        self.stop_robot = stop_robot
        self.state_file = Path(state_file) if state_file else None
        self._latch = threading.Event()
        # press (operator thread) and clear (event loop) set the latch and its facts under it; it is held for a
        # few assignments only, never around the robot's stop or the state file, so a press never waits long
        self._lock = threading.Lock()
        self.latched_at: float | None = None   # wall clock, comparable with the operator's
        self.reason: str | None = None

    @property
    def latched(self) -> bool:
        return self._latch.is_set()

    def press(self, reason: str = "emergency stop from the operator") -> dict:
        """Latch and stop the robot now; the facts of the press (the operator's answer)."""
        with self._lock:   # the latch and its facts together: a clear racing this press sees both or neither
            self._latch.set()   # the loop refuses every action it decides from here on
            if self.latched_at is None:
                self.latched_at, self.reason = time.time(), reason
            facts = {"estop": True, "latched_at": self.latched_at, "reason": self.reason}
        try:
            self.stop_robot()
            held = True
        except Exception:   # the latch stands whatever the driver did; the operator is told
            log.exception("the backend's emergency stop failed; the latch is set")
            held = False
        self._write(running=True)
        return {**facts, "held": held}

    def clear(self) -> None:
        """The operator's release (``clear-estop``)."""
        with self._lock:
            self._latch.clear()
            self.latched_at = self.reason = None
        self._write(running=True)

    # ------------------------------------------------------------ across restarts
    def restore(self) -> str | None:
        """At start: latch (and stop) when the previous bridge ended uncleanly or left the e-stop latched; the
        reason, or None when it starts free. Marks this process as running."""
        previous = self._read()
        reason = None
        if previous.get("running"):
            reason = ("unclean restart: the previous bridge process ended without a clean shutdown (crash, kill or "
                      "power loss); check the robot and the scene, then clear-estop")
        elif previous.get("estop"):
            reason = f"latched before the restart ({previous.get('reason')}); clear-estop once the scene is safe"
        if reason is not None:
            self.press(reason)
        else:
            self._write(running=True)
        return reason

    def mark_clean_exit(self) -> None:
        """The bridge stopped on purpose (operator shutdown, SIGINT, SIGTERM): the next start is not unclean."""
        self._write(running=False)

    def _read(self) -> dict:
        if self.state_file is None or not self.state_file.is_file():
            return {}
        try:
            state = json.loads(self.state_file.read_text())
        except (OSError, ValueError):   # unreadable: assume the worst, the robot starts latched
            return {"running": True}
        return state if isinstance(state, dict) else {"running": True}

    def _write(self, running: bool) -> None:
        if self.state_file is None:
            return
        with self._lock:
            state = {"running": running, "estop": self.latched, "reason": self.reason,
                     "latched_at": self.latched_at, "pid": os.getpid(), "time": time.time()}
        tmp = self.state_file.with_name(self.state_file.name + ".tmp")
        try:
            tmp.write_text(json.dumps(state))
            os.replace(tmp, self.state_file)   # atomic: a crash mid-write leaves the old state, never half a file
        except OSError:
            log.exception("could not record the bridge state in %s", self.state_file)
