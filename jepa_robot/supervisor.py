"""``jepa-robot-bridge supervise``: run the bridge, and after a crash restart it with the e-stop latched.

The bridge runs as a child process (``serve ... --state-file FILE``). A clean stop (an operator's ``shutdown``,
SIGINT or SIGTERM to the supervisor, which passes SIGINT on) ends the supervisor too; a refused set-up (exit 2)
is not retried, since the same file would be refused again. A port held by another process (exit 3: a bridge
still stopping, or a process squatting the port to answer in the bridge's place) never ends it: it says so
loudly and retries, latched, with the same backoff, for as long as it takes. Any other end is a crash
(libzmq's abort, a kill, a bug): the child is started again after ``restart_delay_s`` (doubling up to
``MAX_DELAY_S`` while it keeps crashing within a minute), and because the crashed process never marked its
state file clean, the new bridge starts with the e-stop latched and stops the robot at once
(``estop.EStop.restore``); it moves again only after an operator's ``clear-estop``. The supervisor does not rely
on the state file alone: every restart is also told to start latched (``--start-latched``), and a state file it
cannot write and replace is refused before the first start (exit 2), so a bridge is never restarted unlatched.
On the robot computer systemd runs this supervisor (deploy/robot/jepa-robot-bridge.service) and restarts it if
it dies itself.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time

from jepa_robot.estop import EStop

EXIT_REFUSED = 2
EXIT_PORT_BUSY = 3   # serve could not bind a port another process holds (jepa_robot.cli.EXIT_PORT_BUSY)
MAX_DELAY_S = 30.0
STABLE_S = 60.0     # a bridge that ran this long before crashing restarts after the first delay again


def describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit status {code}"


def _first_to_go() -> None:
    """In the child before it starts: out of memory (the unit's MemoryMax), the kernel ends the bridge, which this
    supervisor restarts latched, rather than this supervisor."""
    try:
        with open("/proc/self/oom_score_adj", "w") as f:
            f.write("500")
    except OSError:   # not Linux, or no /proc: the kernel picks the largest process, the bridge, anyway
        pass


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
                                  "--state-file", state_file, *latched], preexec_fn=_first_to_go)
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
        if code == EXIT_PORT_BUSY:
            print(f"supervisor: WARNING the bridge could not bind its port: another process holds it (see above). It "
                  "may be a process answering operators in the bridge's place: its e-stop answers stop nothing, and "
                  "operator commands with the credential report it ('could not prove it is the robot bridge'). Use "
                  "the hardware e-stop if the robot must stop; find the process with ss -ltnp and stop it. Retry "
                  f"{restarts + 1} in {delay:g}s, with the e-stop latched", file=sys.stderr, flush=True)
        else:
            print(f"supervisor: the bridge ended with {describe_exit(code)}: restart {restarts + 1} in {delay:g}s, "
                  "with the e-stop latched (clear-estop once the robot and the scene are checked)",
                  file=sys.stderr, flush=True)
        why = "could not bind its port (held by another process)" if code == EXIT_PORT_BUSY else \
            f"ended with {describe_exit(code)}"
        latched = ["--start-latched", f"restarted by the supervisor after the bridge {why}; check the robot and the "
                                      "scene, then clear-estop"]
        time.sleep(delay)
        if stopping:
            return 0
        delay = min(MAX_DELAY_S, delay * 2)
        restarts += 1
