"""``jepa-robot-bridge``: operator commands answered here, everything else handed to the full command line.

    jepa-robot-bridge estop | clear-estop | home | status | shutdown [--operator tcp://host:5556]
    jepa-robot-bridge confirm success|failure [--operator ...]
    jepa-robot-bridge serve | check | bench | keys | observe ...   (jepa_robot.cli)

The operator commands import only ZeroMQ and msgpack, so an e-stop is sent within tens of milliseconds of
pressing Enter. With the operator credential (the bridge's user, or --operator-secret) every answer is checked:
one the bridge did not prove (a process squatting the operator port) exits 1 naming it; without the credential
``estop`` and ``status`` still work and say on stderr that their answer is unverified.

Other subcommands need the simulator, numpy and the safety models; for them this process
replaces itself with ``python -m jepa_robot.cli`` (a new program, not an import), which keeps this
package free of the heavy stack.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

from jepa_robot.operator import DEFAULT_OPERATOR, SECRET_ENV, OperatorClient, OperatorError

# the operator socket the commands talk to: --operator, else JEPA_ROBOT_OPERATOR, else the loopback default
OPERATOR_ENV = "JEPA_ROBOT_OPERATOR"

OPERATOR_COMMANDS = ("estop", "clear-estop", "confirm", "home", "status", "shutdown")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jepa-robot-bridge", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    default = os.environ.get(OPERATOR_ENV) or DEFAULT_OPERATOR
    where = f"operator socket (default {default}: ${OPERATOR_ENV}, else {DEFAULT_OPERATOR})"
    secret = (f"the operator credential the bridge made (default ${SECRET_ENV}, else "
              "~/.config/jepa-robot/operator.secret); clear-estop, home, confirm and shutdown need it, and with it "
              "every answer is checked to come from the bridge")
    commands = [sub.add_parser(name, help=text) for name, text in (
        ("estop", "latch the emergency stop (takes effect mid-chunk; any local process may)"),
        ("clear-estop", "release the emergency stop (the operator's credential)"),
        ("home", "drive the robot home (the operator's credential)"), ("status", "print the bridge status"),
        ("shutdown", "stop the bridge (the operator's credential)"))]
    confirm = sub.add_parser("confirm", help="confirm the episode outcome (the operator's credential)")
    confirm.add_argument("outcome", choices=("success", "failure"))
    for cmd in (*commands, confirm):
        cmd.add_argument("--operator", default=default, help=where)
        cmd.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the bridge")
        cmd.add_argument("--operator-secret", metavar="FILE", help=secret)
        cmd.add_argument("--curve-server-key", metavar="FILE",
                         help="a network operator socket: the bridge's public key (bridge.key)")
        cmd.add_argument("--curve-client-key", metavar="FILE",
                         help="a network operator socket: this operator's secret key (NAME.key_secret)")
    return parser


def _wait_gone(pid, timeout_s: float) -> bool | None:
    """Whether the bridge's process ended within ``timeout_s`` (None: the bridge did not say its pid)."""
    if not isinstance(pid, int) or pid <= 0:
        return None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:   # alive, another user's
            pass
        time.sleep(0.05)
    return False


def run_operator_command(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    try:
        op = OperatorClient(args.operator, timeout_s=args.timeout, secret_file=args.operator_secret,
                            curve_server_key=args.curve_server_key, curve_client_key=args.curve_client_key)
    except OperatorError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    with op:
        try:
            if args.command == "shutdown":
                pid = op.status().get("pid")
                op.shutdown()
                # answered is not gone: the bridge still holds its ports while it stops (a new bridge started
                # at once could not bind them), so wait for its process (the operator socket is on this machine)
                result = {"shutdown": True, "exited": _wait_gone(pid, args.timeout)}
            else:
                calls = {"estop": op.estop, "clear-estop": op.clear_estop, "home": op.home, "status": op.status,
                         "confirm": lambda: op.confirm(args.outcome == "success")}
                result = calls[args.command]()
        except (OperatorError, TimeoutError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    if result.get("verified") is False:
        print(f"note: this answer is unverified: without the operator credential ({op.secret_file}) this client "
              "cannot check that the robot bridge sent it; if the robot must stop, the hardware e-stop does",
              file=sys.stderr)
    print(json.dumps(result, indent=2, default=str))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``jepa-robot-bridge``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in OPERATOR_COMMANDS:
        return run_operator_command(argv)
    command = [sys.executable, "-m", "jepa_robot.cli", *argv]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(sys.executable, command)   # does not return


if __name__ == "__main__":
    sys.exit(main())
