"""The operator socket, served by a thread of its own so that no other traffic can block the e-stop.

The socket is a REP: each request must get exactly one reply or the socket refuses every later one, so the
reply is sent in a ``finally``, whatever the request held. The e-stop does not wait for the bridge's event
loop: this thread latches it (``estop_latch``, a ``threading.Event``) before anything else, and the loop
checks the latch before it decodes any control message and before every action it applies. Only then does
the thread ask the loop to do the rest (hold, interrupt the episode, answer a client waiting for a
confirmation) and report its status; if the loop does not answer within ``estop_wait_s`` (it may be inside a
long backend call) the reply says the latch is set and the loop has not yet acknowledged it.

Every other operator command (status, confirm, home, clear_estop, shutdown) runs on the event loop, which owns
the robot, through ``call_loop``; a loop that does not answer in time gets the operator a clear error.
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable

import zmq

from jepa_envs.real_robot import protocol as P
from jepa_envs.real_robot.wire import decode_request, encode_reply

log = logging.getLogger(__name__)

OPERATOR_COMMANDS = (P.OP_ESTOP, P.OP_CLEAR_ESTOP, P.OP_CONFIRM, P.OP_HOME, P.OP_STATUS, P.OP_SHUTDOWN)


class OperatorChannel:
    """Owns the REP operator socket in its own thread; ``handle`` is also the in-process entry (``command``)."""

    def __init__(self, ctx: zmq.Context, address: str, estop_latch: threading.Event,
                 call_loop: Callable[[dict, float], dict], command_timeout_s: float = 5.0,
                 estop_wait_s: float = 0.5):
        self.estop_latch = estop_latch
        self.call_loop = call_loop
        self.command_timeout_s = float(command_timeout_s)
        self.estop_wait_s = float(estop_wait_s)
        self.counters: collections.Counter = collections.Counter()
        self._lock = threading.Lock()      # counters are read by the loop's status()
        self.latched_at: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.sock = ctx.socket(zmq.REP)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.MAXMSGSIZE, P.MAX_OPERATOR_MESSAGE_BYTES)
        try:
            self.sock.bind(address)
        except zmq.ZMQError:
            self.sock.close(linger=0)
            raise
        self.endpoint = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)

    # ------------------------------------------------------------ thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self._serve, name="robot-bridge-operator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close the socket (before the bridge's ZeroMQ context is terminated)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=10)
            self._thread = None
        elif self._thread is None:
            self.sock.close(linger=0)

    def _serve(self) -> None:
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                if not poller.poll(50):
                    continue
                try:
                    frames = self.sock.recv_multipart(zmq.NOBLOCK)
                except zmq.ZMQError:   # nothing was received, so no reply is owed
                    continue
                reply = None
                try:
                    reply = self.answer(frames)
                except Exception as exc:   # a bug here must still answer, or the socket would refuse the e-stop
                    self._count("internal_errors")
                    log.exception("operator request failed")
                    reply = P.error(P.ERR_INTERNAL, f"the bridge failed on this operator request "
                                                    f"({type(exc).__name__}); see its log")
                finally:
                    self.sock.send(encode_reply(reply))
        finally:
            self.sock.close(linger=0)

    def _count(self, name: str) -> None:
        with self._lock:
            self.counters[name] += 1

    def counts(self) -> dict:
        with self._lock:
            return dict(self.counters)

    # ------------------------------------------------------------ requests
    def answer(self, frames: list[bytes]) -> dict:
        """The reply to one operator request, whatever its bytes."""
        if len(frames) != 1:
            self._count("malformed")
            return P.error(P.ERR_BAD_MESSAGE, f"an operator request is one frame; got {len(frames)}")
        message, refusal = decode_request(frames[0])
        if refusal is not None:
            self._count("malformed")
            return refusal
        return self.handle(message)

    def handle(self, message: dict) -> dict:
        """Run one decoded operator command: the e-stop latches here first, the rest runs on the event loop."""
        kind = message.get("type")
        if type(kind) is not str or kind not in OPERATOR_COMMANDS:
            self._count("malformed")
            return P.error(P.ERR_BAD_MESSAGE, f"unknown operator command {str(kind)[:40]!r}; use estop, "
                                              "clear_estop, confirm, home, status, shutdown")
        if kind == P.OP_ESTOP:
            self.estop_latch.set()
            self.latched_at = time.monotonic()
            try:
                return self.call_loop(message, self.estop_wait_s)
            except TimeoutError:
                return {"type": P.RESULT, "ok": True, "status": {
                    "estop": True, "acknowledged": False,
                    "message": f"the e-stop is latched: no further action is applied; the event loop did not "
                               f"confirm the hold within {self.estop_wait_s:.1f}s (it may be inside a long "
                               "backend call); check `jepa-robot-bridge status`"}}
        try:
            return self.call_loop(message, self.command_timeout_s)
        except TimeoutError:
            return P.error(P.ERR_INTERNAL, f"the bridge's event loop did not answer {kind!r} within "
                                           f"{self.command_timeout_s:.1f}s; the e-stop still works (it does not "
                                           "wait for the loop)")
