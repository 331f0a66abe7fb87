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

# v3: liveness by the bridge's pings, echoed on the client's link connection (no ZMTP heartbeats: libzmq 4.3.5
# aborts on them under a flood); an operator ROUTER that answers the e-stop before anything queued
PROTOCOL_VERSION = 3

# operator -> bridge (operator socket, ZeroMQ REQ -> ROUTER); each answered with {"type": "result", ...} or error
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
    """The operator's side: e-stop, confirm, home, status over the bridge's operator socket.

    Usable for as long as it lives: a call that times out (no bridge, or one that did not answer in time) raises
    TimeoutError and leaves a fresh socket behind, so the next call (the e-stop of a long-lived tool) goes out
    at once instead of failing on the REQ socket's state. Nothing is queued while no bridge is connected
    (ZMQ_IMMEDIATE), so an e-stop that timed out is never delivered minutes later to a bridge that starts then.
    """

    def __init__(self, address: str = DEFAULT_OPERATOR, timeout_s: float = 5.0):
        self.address = address
        self.timeout_ms = int(timeout_s * 1000)
        self._ctx = zmq.Context()
        self._sock = self._connect()

    def _connect(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.IMMEDIATE, 1)
        sock.setsockopt(zmq.RCVTIMEO, self.timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, self.timeout_ms)
        sock.connect(self.address)
        return sock

    def _call(self, message: dict) -> dict:
        try:
            self._sock.send(msgpack.packb({"v": PROTOCOL_VERSION, **message}, use_bin_type=True))
            reply = msgpack.unpackb(self._sock.recv(), raw=False, strict_map_key=False)
        except zmq.Again as exc:
            # the REQ socket now waits for a reply that may never come; a new one starts clean
            self._sock.close(linger=0)
            self._sock = self._connect()
            raise TimeoutError(f"no robot bridge answered {message['type']!r} on the operator socket {self.address} "
                               f"within {self.timeout_ms / 1000:g}s; is `jepa-robot-bridge serve` running there?") from exc
        if not isinstance(reply, dict) or reply.get("type") not in (RESULT, ERROR):
            raise OperatorError(f"the bridge sent an unexpected reply {reply!r:.200}")
        if reply["type"] == ERROR:
            raise OperatorError(f"bridge refused {message['type']}: {reply.get('message')}")
        return reply

    def estop(self) -> dict:
        """Latch the emergency stop: the robot holds now, mid-chunk included; no motion until cleared. Returns
        ``{"estop": True, "latched_at": <bridge's wall clock>, "held": <the backend's stop returned>, ...}``,
        answered by the bridge's e-stop path itself (``status`` then shows the interrupted episode)."""
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
