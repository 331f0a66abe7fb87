"""The e-stop latch: pressed from any thread, it stops the robot at once and outlives the bridge's process.

The latch and the start of every motion share one lock (``motion``): the event loop starts an action only
inside ``motion("action")``, which checks the latch under that lock, and ``press`` sets the latch under it. So
once a press has set the latch no action starts, and an action that was already inside ``backend.apply``
finishes first: the press waits for it (at most ``ACTION_WAIT_S``), then calls the backend's
``emergency_stop``, then answers. The answer ``held: true`` therefore means the robot was told to hold after
the last action that will ever start before a ``clear``. A long move (a homing move, a reset) runs inside
``motion("move")``; a press does not wait for it: it latches and calls ``emergency_stop`` concurrently (the
backend's contract), which stops that move, and nothing starts after it either.

``press`` runs in the caller's thread (the operator thread, or the resource guard's), without waiting for the
event loop, the control socket or any other operator request. The loop then interrupts the episode
(``RobotBridge._apply_estop_if_latched``).

Every press, even one on a latch already set, starts a new *generation* of the latch. A ``clear`` releases only
the generation it was received against (the operator thread reads it when the command arrives; the loop clears
later): a press that reached the bridge after the clear keeps the e-stop latched, as a hardware button pressed
while someone starts releasing it stays pressed, and the operator is told to clear again.

With a ``state_file`` the latch survives the process: a bridge started after one that did not stop cleanly
(a crash, a kill, a power cut: its state still says ``running``) starts latched, as does one started after an
e-stop nobody cleared. Only an operator's ``clear`` releases it. A state file that cannot be written is
refused when the bridge starts (``check_state_file``, which runs the very write-and-replace every record
takes: an immutable file, or another user's file in a sticky folder, can be written beside but not replaced):
a latch that cannot be recorded would not survive a crash.
"""
from __future__ import annotations

import json
import logging
import os
import stat
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

log = logging.getLogger(__name__)
MAX_STATE_BYTES = 64 * 1024   # a state file's record is ~200 bytes; a bigger file is unreadable (start latched)

# a press waits this long at most for an action inside ``backend.apply`` (a driver's apply sets a target and
# returns at once, a simulator's steps for milliseconds); past it (a hung driver call) the stop goes out
# concurrently, the answer says so (``action_in_flight``), and the loop holds again when the call returns
ACTION_WAIT_S = 0.05


class EStop:
    """The latch, the robot stop it triggers, and its record on disk."""

    def __init__(self, stop_robot: Callable[[], None], state_file: str | None = None):
        self.stop_robot = stop_robot
        self.state_file = Path(state_file) if state_file else None
        # the latch, its facts and the motion under way change together under this condition's lock; it is held
        # for a few assignments only, never around the robot's stop, a backend call or the state file
        self._cv = threading.Condition(threading.Lock())
        self._latched = False
        self._moving: str | None = None        # "action" or "move" while the loop is inside one
        self._generation = 0                   # bumped by every press (module docstring)
        self.latched_at: float | None = None   # wall clock, comparable with the operator's
        self.reason: str | None = None

    @property
    def latched(self) -> bool:
        return self._latched

    @property
    def generation(self) -> int:
        """The latch's generation now: a ``clear`` received now releases only this one."""
        with self._cv:
            return self._generation

    @contextmanager
    def motion(self, kind: str = "action") -> Iterator[bool]:
        """The loop's only way to move the robot: yields False (start nothing) when the latch is set, else True,
        and a press waits until an ``action`` ends (a ``move`` it stops concurrently)."""
        with self._cv:
            if self._latched:
                free = False
            else:
                free, self._moving = True, kind
        try:
            yield free
        finally:
            if free:
                with self._cv:
                    self._moving = None
                    self._cv.notify_all()

    def press(self, reason: str = "emergency stop from the operator") -> dict:
        """Latch (nothing starts from here on), let an action already under way finish, stop the robot; the
        facts of the press (the operator's answer)."""
        with self._cv:
            newly = not self._latched
            self._latched = True
            self._generation += 1
            if self.latched_at is None:
                self.latched_at, self.reason = time.time(), reason
            facts = {"estop": True, "latched_at": self.latched_at, "reason": self.reason}
            waited = self._cv.wait_for(lambda: self._moving != "action", timeout=ACTION_WAIT_S)
        if not waited:
            log.error("an action was still inside the backend %.3f s after the e-stop; stopping concurrently",
                      ACTION_WAIT_S)
        try:
            self.stop_robot()
            held = True
        except Exception:   # the latch stands whatever the driver did; the operator is told
            log.exception("the backend's emergency stop failed; the latch is set")
            held = False
        if newly:   # a flood of presses costs no disk writes
            self._write(running=True)
        return {**facts, "held": held, "action_in_flight": not waited}

    def clear(self, generation: int | None = None) -> bool:
        """The operator's release (``clear-estop``) of the latch ``generation`` it was received against (None: the
        current one); False, and the latch stays, when a press came after it."""
        with self._cv:
            if generation is not None and generation != self._generation:
                return False
            self._latched = False
            self.latched_at = self.reason = None
        self._write(running=True)
        return True

    # ------------------------------------------------------------ across restarts
    def restore(self) -> str | None:
        """At start: latch (and stop) when the previous bridge ended uncleanly or left the e-stop latched; the
        reason, or None when it starts free. Marks this process as running."""
        self.check_state_file()
        previous = self._read()
        reason = None
        if previous.get("running"):
            reason = ("unclean restart: the previous bridge process ended without a clean shutdown (crash, kill or "
                      "power loss); check the robot and the scene, then clear-estop")
        elif previous.get("estop"):
            before = str(previous.get("reason"))
            reason = before if before.startswith("latched before the restart") else \
                f"latched before the restart ({before}); clear-estop once the scene is safe"
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
            with self.state_file.open("rb") as f:
                text = f.read(MAX_STATE_BYTES + 1)
            if len(text) > MAX_STATE_BYTES:   # a record is ~200 bytes: this is not one
                return {"running": True}
            state = json.loads(text)
        except Exception:   # unreadable in any way (OSError, bad JSON or UTF-8, RecursionError from deep nesting,
            return {"running": True}   # MemoryError): assume the worst, the robot starts latched
        return state if isinstance(state, dict) else {"running": True}

    def check_state_file(self) -> None:
        """Refuse (OSError naming the file and the fix) a state file this process cannot record the latch in: the
        latch would not survive a crash, and a supervisor would restart the bridge unlatched. It takes the path
        every record takes (a sibling written, then renamed over the file), keeping what the file held."""
        if self.state_file is None:
            return
        try:
            mode = os.stat(self.state_file).st_mode
        except OSError:   # none yet (or not reachable): the probe below finds out
            mode = None
        if mode is not None and not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
            # a device, a FIFO or a socket: every record would replace it with a regular file (as root: /dev/null,
            # a serial port), so it is refused, as the credential file is
            raise OSError(f"the e-stop state file {self.state_file} is not a regular file (a device, a FIFO or a "
                          "socket) and would be replaced by one; pass a file path in a folder this user owns "
                          "(e.g. /var/lib/jepa-robot/bridge-state.json)")
        probe = self.state_file.with_name(self.state_file.name + ".tmp")
        try:
            if self.state_file.is_dir():
                raise IsADirectoryError(f"the e-stop state file {self.state_file} is a folder; pass a file path in "
                                        f"it, e.g. {self.state_file / 'bridge-state.json'}")
            existed = self.state_file.is_file()
            kept = self.state_file.read_bytes() if existed else b"{}"
            probe.write_bytes(kept)
            os.replace(probe, self.state_file)   # what _write does: an immutable file or another user's in a
            if not existed:                      # sticky folder (/tmp) is refused here, not at the first press
                self.state_file.unlink()
        except IsADirectoryError as exc:
            if exc.errno is None:   # ours, above
                raise
            problem = exc
        except OSError as exc:
            problem = exc
        else:
            return
        try:
            probe.unlink()
        except OSError:
            pass
        raise OSError(f"the e-stop state file {self.state_file} cannot be written and replaced "
                      f"({problem.strerror or problem}): the latch would not survive a crash; pass a --state-file in "
                      "a folder this user owns (e.g. /var/lib/jepa-robot/bridge-state.json), not another user's "
                      "file nor an immutable one") from None

    def _write(self, running: bool) -> None:
        if self.state_file is None:
            return
        with self._cv:
            state = {"running": running, "estop": self.latched, "reason": self.reason,
                     "latched_at": self.latched_at, "pid": os.getpid(), "time": time.time()}
        tmp = self.state_file.with_name(self.state_file.name + ".tmp")
        try:
            tmp.write_text(json.dumps(state))
            os.replace(tmp, self.state_file)   # atomic: a crash mid-write leaves the old state, never half a file
        except OSError:
            log.exception("could not record the bridge state in %s", self.state_file)
