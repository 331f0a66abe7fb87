"""The robot operator's side of the bridge, import-light: e-stop, clear, confirm, home, status, shutdown.

This package imports only ZeroMQ and msgpack (no numpy, gymnasium or torch), so ``jepa-robot-bridge estop``
starts in a few tens of milliseconds; it is also the single home of the protocol version and of the operator
messages, which ``jepa_envs.real_robot.protocol`` re-exports for the bridge. It imports no other project
package, and any may import it.

    from jepa_operator import OperatorClient
    with OperatorClient("tcp://127.0.0.1:5556") as op:
        op.estop()
"""
from __future__ import annotations

import msgpack
import zmq

PROTOCOL_VERSION = 2   # v2: per-session seq required, liveness by ZMTP heartbeats, observe / stream

# operator -> bridge (operator socket, ZeroMQ REQ -> REP); each answered with {"type": "result", ...} or error
OP_ESTOP = "estop"
OP_CLEAR_ESTOP = "clear_estop"
OP_CONFIRM = "confirm"
OP_HOME = "home"
OP_STATUS = "status"
OP_SHUTDOWN = "shutdown"
RESULT = "result"
ERROR = "error"
DEFAULT_OPERATOR = "tcp://127.0.0.1:5556"


class OperatorError(RuntimeError):
    """The bridge refused an operator command; the message says why."""


class OperatorClient:
    """The operator's side: e-stop, confirm, home, status over the bridge's operator socket."""

    def __init__(self, address: str = DEFAULT_OPERATOR, timeout_s: float = 5.0):
        self.address = address
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.REQ)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
        self._sock.setsockopt(zmq.SNDTIMEO, int(timeout_s * 1000))
        self._sock.connect(address)

    def _call(self, message: dict) -> dict:
        try:
            self._sock.send(msgpack.packb({"v": PROTOCOL_VERSION, **message}, use_bin_type=True))
            reply = msgpack.unpackb(self._sock.recv(), raw=False, strict_map_key=False)
        except zmq.Again as exc:
            raise TimeoutError(f"no robot bridge answered on the operator socket {self.address}; "
                               "is `jepa-robot-bridge serve` running there?") from exc
        if not isinstance(reply, dict) or reply.get("type") not in (RESULT, ERROR):
            raise OperatorError(f"the bridge sent an unexpected reply {reply!r:.200}")
        if reply["type"] == ERROR:
            raise OperatorError(f"bridge refused {message['type']}: {reply.get('message')}")
        return reply

    def estop(self) -> dict:
        """Latch the emergency stop: the robot holds now, mid-chunk included; no motion until cleared."""
        return self._call({"type": OP_ESTOP})["status"]

    def clear_estop(self) -> dict:
        return self._call({"type": OP_CLEAR_ESTOP})["status"]

    def confirm(self, success: bool) -> dict:
        """Confirm the episode's outcome (at budget end, or early when the goal is reached)."""
        return self._call({"type": OP_CONFIRM, "success": bool(success)})["status"]

    def home(self) -> dict:
        return self._call({"type": OP_HOME})["status"]

    def status(self) -> dict:
        return self._call({"type": OP_STATUS})["status"]

    def shutdown(self) -> None:
        self._call({"type": OP_SHUTDOWN})

    def close(self) -> None:
        self._sock.close(linger=0)
        self._ctx.term()

    def __enter__(self) -> "OperatorClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
