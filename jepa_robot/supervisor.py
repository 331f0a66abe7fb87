"""``jepa-robot-bridge supervise``: run the bridge, and after a crash restart it with the e-stop latched.

The bridge runs as a child process (``serve ... --state-file FILE``). A clean stop (an operator's ``shutdown``,
SIGINT or SIGTERM to the supervisor, which passes SIGINT on) ends the supervisor too; a refused set-up (exit 2)
is not retried, since the same file would be refused again. Any other end is a crash (libzmq's abort, a kill, a
bug): the child is started again after ``restart_delay_s`` (doubling up to ``MAX_DELAY_S`` while it keeps
crashing within a minute), and because the crashed process never marked its state file clean, the new bridge
starts with the e-stop latched and stops the robot at once (``estop.EStop.restore``); it moves again only
after an operator's ``clear-estop``. The supervisor does not rely on the state file alone: every restart is
also told to start latched (``--start-latched``), and a state file it cannot write is refused before the first
start (exit 2), so a bridge is never restarted unlatched. On the robot computer systemd runs this supervisor
(deploy/robot/jepa-robot-bridge.service) and restarts it if it dies itself.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time

from jepa_robot.estop import EStop

EXIT_REFUSED = 2
MAX_DELAY_S = 30.0
STABLE_S = 60.0     # a bridge that ran this long before crashing restarts after the first delay again


def describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit status {code}"


def supervise(serve_args: list[str], state_file: str, restart_delay_s: float = 1.0) -> int:
    """Run ``serve serve_args --state-file state_file`` until it stops cleanly; restart it after a crash."""
    child: subprocess.Popen | None = None
    stopping = False

    def stop(signum, frame) -> None:
        nonlocal stopping
        stopping = True
        if child is not None and child.poll() is None:
            child.send_signal(signal.SIGINT)   # the bridge's clean stop: it holds the robot and marks its state

    try:
        EStop(lambda: None, state_file).check_state_file()
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_REFUSED
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    delay = restart_delay_s
    restarts = 0
    latched: list[str] = []
    while True:
        started = time.monotonic()
        child = subprocess.Popen([sys.executable, "-m", "jepa_robot.cli", "serve", *serve_args,
                                  "--state-file", state_file, *latched])
        code = child.wait()
        if stopping or code == 0:
            print(f"supervisor: the bridge stopped cleanly after {restarts} restart(s)", file=sys.stderr, flush=True)
            return 0
        if code == EXIT_REFUSED:
            print("supervisor: the bridge refused its set-up (see above); fix it, then start again",
                  file=sys.stderr, flush=True)
            return code
        if time.monotonic() - started > STABLE_S:
            delay = restart_delay_s
        print(f"supervisor: the bridge ended with {describe_exit(code)}: restart {restarts + 1} in {delay:g}s, "
              "with the e-stop latched (clear-estop once the robot and the scene are checked)",
              file=sys.stderr, flush=True)
        latched = ["--start-latched", f"restarted by the supervisor after the bridge ended with "
                                      f"{describe_exit(code)}; check the robot and the scene, then clear-estop"]
        time.sleep(delay)
        if stopping:
            return 0
        delay = min(MAX_DELAY_S, delay * 2)
        restarts += 1
