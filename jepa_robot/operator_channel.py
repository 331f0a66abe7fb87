"""The operator socket, served by a thread of its own: the e-stop is answered before anything else is done.

The socket is a ROUTER (operators connect with REQ, ``jepa_robot.operator.OperatorClient``), so one operator's request
never waits for another's answer. Each turn the thread reads every request that is waiting (up to
``TURN_REQUESTS``), and an e-stop is pressed the moment its frame is read: a frame equal to one of the exact
e-stop messages (``jepa_robot.operator.ESTOP_FRAMES``) needs no decoding, and ``EStop.press`` latches and stops the
robot in this thread; the answer goes out before the next frame is read. An e-stop written another way (extra
keys, padding) is an ordinary request: decoded within the budgets below, then pressed. The e-stop waits for at
most one receive per connection ahead of it (the ROUTER takes one message per connection in turn), never for a
decode, the event loop, the control socket or another operator request.

Who may ask what: ``estop`` and ``status`` are open to every local process; ``clear_estop``, ``home``,
``confirm`` and ``shutdown`` need the operator credential, sent as the first of two frames
(``jepa_robot.operator``), compared in constant time before anything is decoded; without it they are refused
(``unauthorized``) and change nothing. An authenticated request is also exempt from the shared budget below, so
a flood of strangers never crowds the operator out.

Then the turn's other frames are decoded within two budgets: ``OPERATOR_PEER_RATE`` requests a second per
connection (beyond it, one prepared ``rate_limited`` answer, unread) and ``OPERATOR_BYTES_RATE`` bytes a second
for all unauthenticated connections together (beyond it, the same prepared answer, unread; counted as
``operator_dropped``). A frame is charged to that budget only when it fits in what is left, so the budget never
goes negative and is full again a quarter of a second after any flood ends. Every request gets an answer:
its result, ``busy``, ``rate_limited`` or the refusal that names the problem; none is left to time out. After a
full turn of refused frames the thread pauses ``FLOOD_PAUSE_S``, so a flood takes a bounded share of the CPU
and the GIL from the event loop; an e-stop then waits at most that pause plus one receive per connection.

Every other command (status, confirm, home, clear_estop, shutdown) runs on the event loop, which owns the robot:
the thread forwards it over an inproc socket the loop polls, and sends the loop's answer back when it comes,
serving new requests (e-stops first) meanwhile. At most ``MAX_PENDING`` commands wait for the loop; more are
answered ``busy`` at once. ``handle`` is the same entry for callers inside the bridge's process
(``RobotBridge.command``, trusted: no credential), whose commands wait in a queue the loop serves on the same
turn (``serve_loop``).
"""
from __future__ import annotations

import collections
import hmac
import itertools
import logging
import queue
import threading
import time
from typing import Callable

import zmq

from jepa_robot.operator import ESTOP_FRAMES, ERR_UNAUTHORIZED, PRIVILEGED_COMMANDS

from jepa_robot import protocol as P
from jepa_robot.endpoints import OPERATOR_IO_AFFINITY, realtime_thread
from jepa_robot.estop import EStop
from jepa_robot.wire import PeerBuckets, decode_request, encode_reply

log = logging.getLogger(__name__)

OPERATOR_COMMANDS = (P.OP_ESTOP, P.OP_CLEAR_ESTOP, P.OP_CONFIRM, P.OP_HOME, P.OP_STATUS, P.OP_SHUTDOWN)
TURN_REQUESTS = 512     # requests read per turn (each e-stop among them pressed as soon as it is read)
FLOOD_PAUSE_S = 0.001  # after a full turn of refused frames (a flood): the thread's share of CPU and GIL is bounded
MAX_PENDING = 64        # operator commands waiting for the event loop
OPERATOR_PEER_RATE = 100.0      # requests a second one operator connection gets decoded (bursts of ...)
OPERATOR_PEER_BURST = 50
OPERATOR_BYTES_RATE = 256 * 1024.0   # bytes a second decoded for all operator connections together (bursts of ...)
OPERATOR_BYTES_BURST = 64 * 1024
REMEMBERED_OPERATORS = 4096
OPERATOR_RCVHWM = 8     # messages queued per operator connection
_OPERATOR_RATE_LIMITED = P.encode(P.error(
    P.ERR_RATE, f"the operator socket decodes up to {OPERATOR_PEER_RATE:g} requests a second per connection and "
                f"{OPERATOR_BYTES_RATE / 1024:g} KiB a second for all unauthenticated ones; this one was refused "
                "unread (an e-stop never is; the operator's credential skips the shared budget); try again"))
_ids = itertools.count()


def _route(frames: list[bytes]) -> list[bytes]:
    """The sender's identity and, for a REQ socket, its empty delimiter: what the answer goes back with."""
    return frames[:2] if len(frames) >= 3 and frames[1] == b"" else frames[:1]


class OperatorChannel:
    """Owns the operator ROUTER in its own thread; ``loop_sockets`` are the event loop's end of the forwarding."""

    def __init__(self, ctx: zmq.Context, address: str, estop: EStop, answer: Callable[[dict], dict],
                 on_failure: Callable[[], None], secret: bytes, command_timeout_s: float = 5.0,
                 secret_file: str = "the operator credential file",
                 curve: Callable[[zmq.Socket], None] | None = None, rt_priority: int | None = None):
        self.estop = estop
        self.secret = secret            # the operator credential (operator.ensure_operator_secret)
        self.secret_file = secret_file
        self.rt_priority = rt_priority  # SCHED_FIFO for this thread (endpoints.realtime_thread), None: normal
        self.answer = answer            # the event loop's command (it owns the robot); may raise
        self.on_failure = on_failure    # called when ``answer`` fails: the robot holds
        self.command_timeout_s = float(command_timeout_s)
        self.loop_thread: int | None = None        # the event loop's thread, once it runs
        self._in_process: queue.Queue = queue.Queue()   # (message, reply box) from ``handle``
        self.counters: collections.Counter = collections.Counter()
        self._lock = threading.Lock()      # counters are read by the loop's status()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pending = 0
        self._peers = PeerBuckets(OPERATOR_PEER_RATE, OPERATOR_PEER_BURST, REMEMBERED_OPERATORS)
        self._global = [float(OPERATOR_BYTES_BURST), time.monotonic()]
        self.sock = ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.MAXMSGSIZE, P.MAX_OPERATOR_MESSAGE_BYTES)
        self.sock.setsockopt(zmq.AFFINITY, OPERATOR_IO_AFFINITY)   # an I/O thread of its own (endpoints.py)
        # an operator has one request in flight (REQ); a flood's connection is read only as fast as the thread
        # drains it, so its I/O thread's turns stay short and the e-stop's bytes are not queued behind them
        self.sock.setsockopt(zmq.RCVHWM, OPERATOR_RCVHWM)
        try:
            if curve is not None:
                curve(self.sock)
            self.sock.bind(address)
        except (zmq.ZMQError, ValueError, OSError):
            self.sock.close(linger=0)
            raise
        self.endpoint = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)
        name = f"inproc://robot-bridge-operator-{next(_ids)}"
        self._to_loop, self._from_loop = ctx.socket(zmq.PUSH), ctx.socket(zmq.PULL)
        self._to_loop.bind(name + "-commands")
        self._from_loop.bind(name + "-answers")
        # the event loop's ends: it reads commands from the first and writes answers to the second
        self.loop_commands, self.loop_answers = ctx.socket(zmq.PULL), ctx.socket(zmq.PUSH)
        self.loop_commands.connect(name + "-commands")
        self.loop_answers.connect(name + "-answers")

    # ------------------------------------------------------------ thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self._serve, name="robot-bridge-operator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close every socket of the channel (before the ZeroMQ context is terminated)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=10)
            self._thread = None
        elif self._thread is None:
            self._close_thread_sockets()
        for sock in (self.loop_commands, self.loop_answers):
            sock.close(linger=0)

    def _close_thread_sockets(self) -> None:
        for sock in (self._to_loop, self._from_loop):
            sock.close(linger=0)
        self.sock.close(linger=500)   # the last answers (a shutdown's) still go out

    def _serve(self) -> None:
        realtime_thread(self.rt_priority)
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        poller.register(self._from_loop, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                try:
                    events = dict(poller.poll(50))
                    if self.sock in events and self._serve_requests() >= TURN_REQUESTS and FLOOD_PAUSE_S:
                        # a full turn of refused frames: a flood. Pausing costs an e-stop at most this long (it
                        # is then at most one frame per connection behind) and keeps this thread from taking the
                        # event loop's CPU and the GIL at the flood's rate
                        time.sleep(FLOOD_PAUSE_S)
                    if self._from_loop in events:
                        self._send_answers()
                except Exception:   # never reached by input; a bug here must not end the e-stop's thread
                    self._count("internal_errors")
                    log.exception("operator thread error; the e-stop thread goes on")
                    time.sleep(0.001)
            if self._from_loop.poll(200):   # the loop's last answer (a shutdown) was sent just before it stopped
                self._send_answers()
        finally:
            self._close_thread_sockets()

    def _serve_requests(self) -> int:
        """One turn: read what is waiting, pressing each exact e-stop the moment its frame is read and refusing
        what is over budget unread; then the rest, within the per-connection rate (module docstring). Returns
        how many frames were refused unread."""
        later, dropped = [], 0
        g = self._global   # all unauthenticated connections' decoding budget, refilled once a turn
        now = time.monotonic()
        g[0] = min(float(OPERATOR_BYTES_BURST), g[0] + (now - g[1]) * OPERATOR_BYTES_RATE)
        g[1] = now
        for _ in range(TURN_REQUESTS):
            try:
                frames = self.sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            route = _route(frames)
            parts = frames[len(route):]
            if len(parts) == 1 and parts[0] in ESTOP_FRAMES:
                self._send(route, self._press())
                continue
            authenticated = len(parts) == 2 and hmac.compare_digest(parts[0], self.secret)
            if not authenticated:
                cost = max(sum(len(p) for p in parts), 64)
                if g[0] < cost:   # the shared budget is spent: a flood; refused unread, the budget untouched
                    dropped += 1
                    self._send(route, _OPERATOR_RATE_LIMITED)
                    continue
                g[0] -= cost
            later.append((frames[0], route, parts, authenticated))
        refused = dropped
        for identity, route, parts, authenticated in later:
            if self._peer_over_rate(identity, now):   # this connection's own limit: told so, unread
                refused += 1
                self._send(route, _OPERATOR_RATE_LIMITED)
                continue
            self._handle(route, *self._decode(parts, authenticated), authenticated)
        if refused:
            with self._lock:
                for name, count in (("operator_dropped", dropped), ("operator_rate_limited", refused - dropped)):
                    if count:
                        self.counters[name] += count
        return refused

    def _handle(self, route: list[bytes], message: dict | None, refusal: dict | None, authenticated: bool) -> None:
        if refusal is not None:
            self._send(route, refusal)
        elif message["type"] == P.OP_ESTOP:   # one that did not look like one (padded, reordered): pressed now
            self._send(route, self._press())
        elif message["type"] in PRIVILEGED_COMMANDS and not authenticated:
            self._count("operator_unauthorized")
            self._send(route, P.error(ERR_UNAUTHORIZED, f"{message['type']} is the operator's command and needs the "
                                                        f"operator credential ({self.secret_file}, readable by the "
                                                        "bridge's user only: run `jepa-robot-bridge "
                                                        f"{message['type'].replace('_', '-')}` as that user, or "
                                                        "pass --operator-secret FILE); nothing was changed"))
        elif self._pending >= MAX_PENDING:
            self._count("operator_busy")
            self._send(route, P.error(P.ERR_BUSY, f"{self._pending} operator commands are waiting for the "
                                                  "bridge's event loop; try again (the e-stop never waits)"))
        else:
            self._pending += 1
            self._to_loop.send_multipart([*route, P.encode(message)])

    def _peer_over_rate(self, identity: bytes, now: float) -> bool:
        """One connection's token bucket: OPERATOR_PEER_RATE requests a second, bursts of OPERATOR_PEER_BURST."""
        bucket = self._peers.refilled(identity, now)
        if bucket[0] < 1.0:
            return True
        bucket[0] -= 1.0
        return False

    def _send_answers(self) -> None:
        while True:
            try:
                frames = self._from_loop.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            self._pending -= 1
            self._send(frames[:-1], frames[-1])

    def _send(self, route: list[bytes], reply: dict | bytes) -> None:
        payload = reply if isinstance(reply, bytes) else encode_reply(reply)
        try:
            self.sock.send_multipart([*route, payload], zmq.NOBLOCK)
        except zmq.ZMQError:   # the operator's connection is gone or not reading; nothing is owed
            self._count("undeliverable")

    def _decode(self, parts: list[bytes], authenticated: bool) -> tuple[dict | None, dict | None]:
        """(message, None) for a known operator command, else (None, the refusal that answers it). ``parts``
        are the request's frames after the route: the message, or the credential and the message."""
        if len(parts) == 2 and not authenticated:
            self._count("operator_unauthorized")
            return None, P.error(ERR_UNAUTHORIZED, "the operator credential sent does not match this bridge's "
                                                   f"({self.secret_file}); nothing was changed")
        if len(parts) not in (1, 2):
            self._count("malformed")
            return None, P.error(P.ERR_BAD_MESSAGE, f"an operator request is one frame (or the credential and "
                                                    f"one frame); got {len(parts)}")
        message, refusal = decode_request(parts[-1])
        if refusal is None and message["type"] not in OPERATOR_COMMANDS:
            message, refusal = None, P.error(P.ERR_BAD_MESSAGE, f"unknown operator command {message['type'][:40]!r}; "
                                                                "use estop, clear_estop, confirm, home, status, "
                                                                "shutdown")
        if refusal is not None:
            self._count("malformed")
        return message, refusal

    def _press(self) -> dict:
        self._count("estops")
        facts = self.estop.press()
        text = ("the e-stop is latched and the robot was told to hold; the episode ends as interrupted/estop"
                if facts["held"] else "the e-stop is latched (no action is applied) but the backend's stop "
                                      "FAILED: use the hardware e-stop; see the bridge log")
        return {"type": P.RESULT, "ok": True, "status": {**facts, "message": text}}

    def _count(self, name: str) -> None:
        with self._lock:
            self.counters[name] += 1

    def counts(self) -> dict:
        with self._lock:
            return dict(self.counters)

    # ------------------------------------------------------------ the event loop's side
    def serve_loop(self, commands: int) -> None:
        """On the event loop: answer up to ``commands`` forwarded commands, and the in-process ones."""
        for _ in range(commands):
            try:
                frames = self.loop_commands.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            message, refusal = decode_request(frames[-1])   # decoded once already: a known, versioned command
            self.loop_answers.send_multipart([*frames[:-1], encode_reply(refusal or self._answer(message))])
        while True:
            try:
                message, box = self._in_process.get_nowait()
            except queue.Empty:
                return
            box.put(self._answer(message))

    def _answer(self, message: dict) -> dict:
        try:
            return self.answer(message)
        except (P.ProtocolError, ValueError, TypeError) as exc:
            self._count("malformed")
            return P.error(P.ERR_BAD_MESSAGE, str(exc))
        except Exception as exc:
            self._count("internal_errors")
            log.exception("operator command failed")
            self.on_failure()
            return P.error(P.ERR_INTERNAL, f"the bridge failed on this command ({type(exc).__name__}: {exc}); "
                                           "the robot holds")

    # ------------------------------------------------------------ in-process callers
    def handle(self, message: dict) -> dict:
        """One decoded operator command from inside the bridge's process (any thread): the e-stop latches here,
        the rest runs on the event loop (TimeoutError's reply when it does not answer in time)."""
        kind = message.get("type")
        if type(kind) is not str or kind not in OPERATOR_COMMANDS:
            self._count("malformed")
            return P.error(P.ERR_BAD_MESSAGE, f"unknown operator command {str(kind)[:40]!r}; use estop, "
                                              "clear_estop, confirm, home, status, shutdown")
        if kind == P.OP_ESTOP:
            return self._press()
        if threading.get_ident() == self.loop_thread:
            return self._answer(message)
        box: queue.Queue = queue.Queue(maxsize=1)
        self._in_process.put((message, box))
        deadline = time.monotonic() + self.command_timeout_s
        while time.monotonic() < deadline and self.loop_thread is not None:
            try:
                return box.get(timeout=0.05)
            except queue.Empty:
                continue
        return P.error(P.ERR_INTERNAL, f"the bridge's event loop did not answer {kind!r} within "
                                       f"{self.command_timeout_s:.1f}s; the e-stop still works (it does not "
                                       "wait for the loop)")
