"""The operator socket, served by a thread of its own: the e-stop is answered before anything else is done.

The socket is a ROUTER (operators connect with REQ, ``jepa_robot.operator.OperatorClient``), so one operator's request
never waits for another's answer. Each turn the thread reads every request that is waiting (up to
``TURN_REQUESTS``), frame by frame, keeping at most the first ``KEEP_FRAMES`` of a message (the rest of a message
of thousands of frames is read and dropped one frame at a time, never held as a list, and counted as
``operator_too_many_frames``). A message any of whose frames equals one of the exact e-stop messages
(``jepa_robot.operator.ESTOP_FRAMES``) is an e-stop, pressed the moment it is read: ``EStop.press`` latches and
stops the robot in this thread, and the answer goes out before the next message is read (with ``estop_proof``
when the e-stop frame came with the client's 16-byte nonce). An exact ``challenge`` is answered as soon as it is
read too, with a nonce for the operator's next privileged command (``Challenges``). An e-stop written another way
(extra keys, padding) is an ordinary request: decoded within the budgets below, then pressed. The e-stop waits for
at most one message per connection ahead of it (the ROUTER takes one message per connection in turn), never for a
decode, the event loop, the control socket or another operator request.

Who may ask what: ``estop`` and ``status`` are open to every local process; ``clear_estop``, ``home``,
``confirm`` and ``shutdown`` need the operator credential, proven without being sent (``jepa_robot.operator``,
protocol v4): the command's first frame is its MAC, checked in constant time before anything is decoded, and its
body carries a challenge this bridge issued, unexpired and not used before (``Challenges``). Without them they are
refused (``unauthorized``, ``stale_challenge``) and change nothing; the reply to an authenticated command carries
``reply_proof``, and a ``status`` that carries a nonce gets ``status_proof``. The credential file is checked again
at each authenticated command: once it is readable by others or no longer this user's, privileged commands are
refused until the bridge restarts with a new one.

Then the turn's other frames are decoded within two budgets: ``OPERATOR_PEER_RATE`` requests a second per
connection (beyond it, one prepared ``rate_limited`` answer, unread) and ``OPERATOR_BYTES_RATE`` bytes a second
for all unauthenticated connections together (beyond it, the same prepared answer, unread; counted as
``operator_dropped``). A frame is charged to that budget only when it fits in what is left, so the budget never
goes negative and is full again a quarter of a second after any flood ends. An authenticated command skips the
shared budget. Every request gets an answer: its result, ``busy``, ``rate_limited`` or the refusal that names the
problem; none is left to time out. After a full turn of refused frames the thread pauses ``FLOOD_PAUSE_S``, so a
flood takes a bounded share of the CPU and the GIL from the event loop; an e-stop then waits at most that pause
plus one receive per connection.

Every other command (status, confirm, home, clear_estop, shutdown) runs on the event loop, which owns the robot:
the thread forwards it over an inproc socket the loop polls (authenticated commands over one of their own, which
the loop serves first), and sends the loop's answer back when it comes, serving new requests (e-stops first)
meanwhile. At most ``MAX_PENDING`` commands wait for the loop, of which only ``MAX_PENDING -
RESERVED_FOR_OPERATOR`` may be unauthenticated: beyond that they are answered ``busy`` at once, so a flood of
strangers' ``status`` never crowds the operator out. A ``clear_estop`` is forwarded with the latch's generation
read the moment its message was read off the socket (``EStop.clear``): a press read after it, even an e-stop
pressed later in the same turn, keeps the e-stop latched. ``handle`` is
the same entry for callers inside the bridge's process (``RobotBridge.command``, trusted: no credential), whose
commands wait in a queue the loop serves on the same turn (``serve_loop``).
"""
from __future__ import annotations

import collections
import hmac
import itertools
import logging
import os
import queue
import secrets
import struct
import threading
import time
from pathlib import Path
from typing import Callable

import msgpack
import zmq

from jepa_robot.operator import (CHALLENGE_BYTES, CHALLENGE_FRAMES, CHALLENGE_VALID_S, ERR_CHALLENGE, ERR_UNAUTHORIZED,
                                 ESTOP_FRAMES, MAC_BYTES, NONCE_BYTES, PRIVILEGED_COMMANDS, credential_problem,
                                 estop_proof, reply_proof, request_mac, status_proof)

from jepa_robot import protocol as P
from jepa_robot.endpoints import HANDSHAKE_IVL_MS, OPERATOR_IO_AFFINITY, realtime_thread
from jepa_robot.estop import EStop
from jepa_robot.wire import PeerBuckets, decode_request, encode_reply

log = logging.getLogger(__name__)

OPERATOR_COMMANDS = (P.OP_ESTOP, P.OP_CLEAR_ESTOP, P.OP_CONFIRM, P.OP_HOME, P.OP_STATUS, P.OP_SHUTDOWN)
TURN_REQUESTS = 512     # requests read per turn (each e-stop among them pressed as soon as it is read)
FLOOD_PAUSE_S = 0.001  # after a full turn of refused frames (a flood): the thread's share of CPU and GIL is bounded
MAX_PENDING = 80        # operator commands waiting for the event loop ...
RESERVED_FOR_OPERATOR = 16   # ... of which these only authenticated ones may take (strangers: 64, as before)
MAX_PARTS = 2           # an operator request after its route: the message, or a MAC (or the e-stop) and one frame
KEEP_FRAMES = 2 + MAX_PARTS + 1   # identity, REQ delimiter, the parts, and one to tell "too many" apart
OPERATOR_PEER_RATE = 100.0      # requests a second one operator connection gets decoded (bursts of ...)
OPERATOR_PEER_BURST = 50
OPERATOR_BYTES_RATE = 256 * 1024.0   # bytes a second decoded for all operator connections together (bursts of ...)
OPERATOR_BYTES_BURST = 64 * 1024
REMEMBERED_OPERATORS = 4096
OPERATOR_RCVHWM = 8     # messages queued per operator connection
_ESTOP_SIZES = frozenset(len(f) for f in ESTOP_FRAMES)
_OPERATOR_RATE_LIMITED = P.encode(P.error(
    P.ERR_RATE, f"the operator socket decodes up to {OPERATOR_PEER_RATE:g} requests a second per connection and "
                f"{OPERATOR_BYTES_RATE / 1024:g} KiB a second for all unauthenticated ones; this one was refused "
                "unread (an e-stop never is; the operator's authenticated commands skip the shared budget); try "
                "again"))
_TOO_MANY_FRAMES = P.encode(P.error(
    P.ERR_BAD_MESSAGE, f"an operator request is one frame, or a MAC and one frame (at most {MAX_PARTS}); this one had "
                       "more and was dropped unread"))
_ids = itertools.count()


def _route(frames: list[bytes]) -> list[bytes]:
    """The sender's identity and, for a REQ socket, its empty delimiter: what the answer goes back with."""
    return frames[:2] if len(frames) >= 3 and frames[1] == b"" else frames[:1]


class Challenges:
    """Nonces for privileged commands, verifiable without keeping them: the issuing time (ms on this process's
    monotonic clock), 16 random bytes and a 16-byte HMAC of both under a key drawn from the operator secret and
    this process's own random bytes (so a restarted bridge accepts none of its predecessor's). A nonce is good for
    ``valid_s`` seconds and once: the nonces of accepted commands are remembered until they expire (only the
    operator can add to that set, so it stays small)."""

    def __init__(self, secret: bytes, valid_s: float = CHALLENGE_VALID_S):
        self.valid_s = float(valid_s)
        self._key = hmac.digest(secret, b"jepa-robot challenge key\0" + secrets.token_bytes(16), "sha256")
        self._used: dict[bytes, float] = {}   # nonce -> when it expires

    def issue(self, now: float) -> bytes:
        stamp = struct.pack(">Q", int(now * 1000))
        random = secrets.token_bytes(16)
        return stamp + random + hmac.digest(self._key, stamp + random, "sha256")[:16]

    def problem(self, nonce, now: float) -> str | None:
        """Why ``nonce`` may not authorise a command now, or None."""
        if type(nonce) is not bytes or len(nonce) != CHALLENGE_BYTES:
            return "it carries no challenge of this bridge ('challenge': ask for one first)"
        if not hmac.compare_digest(nonce[24:], hmac.digest(self._key, nonce[:24], "sha256")[:16]):
            return "its challenge was not issued by this bridge process (another bridge's, or from before a restart)"
        age = now - struct.unpack(">Q", nonce[:8])[0] / 1000
        if not -1.0 <= age <= self.valid_s:
            return f"its challenge expired ({age:.1f} s old; a challenge is good for {self.valid_s:g} s)"
        if nonce in self._used:
            return "its challenge was used before (a replayed command)"
        return None

    def use(self, nonce: bytes, now: float) -> None:
        """Remember an accepted command's nonce until it expires (and forget the expired ones)."""
        for old in [n for n, until in self._used.items() if until < now]:
            del self._used[old]
        self._used[nonce] = now + self.valid_s + 1.0


class OperatorChannel:
    """Owns the operator ROUTER in its own thread; ``loop_sockets`` are the event loop's end of the forwarding."""

    def __init__(self, ctx: zmq.Context, address: str, estop: EStop, answer: Callable[[dict, int | None], dict],
                 on_failure: Callable[[], None], secret: bytes, command_timeout_s: float = 5.0,
                 secret_file: str = "the operator credential file",
                 curve: Callable[[zmq.Socket], None] | None = None, rt_priority: int | None = None):
        self.estop = estop
        self.secret = secret            # the operator credential (operator.ensure_operator_secret)
        self.secret_file = secret_file
        self.challenges = Challenges(secret)
        self._compromised: str | None = None   # why the credential may no longer be trusted (``_credential_problem``)
        self.rt_priority = rt_priority  # SCHED_FIFO for this thread (endpoints.realtime_thread), None: normal
        self.answer = answer            # the event loop's command (it owns the robot), with the clear's generation
        self.on_failure = on_failure    # called when ``answer`` fails: the robot holds
        self.command_timeout_s = float(command_timeout_s)
        self.loop_thread: int | None = None        # the event loop's thread, once it runs
        self._in_process: queue.Queue = queue.Queue()   # (message, generation, reply box) from ``handle``
        self.counters: collections.Counter = collections.Counter()
        self._lock = threading.Lock()      # counters are read by the loop's status()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pending = {False: 0, True: 0}   # commands waiting for the loop: unauthenticated, authenticated
        self._peers = PeerBuckets(OPERATOR_PEER_RATE, OPERATOR_PEER_BURST, REMEMBERED_OPERATORS)
        self._global = [float(OPERATOR_BYTES_BURST), time.monotonic()]
        self.sock = ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.MAXMSGSIZE, P.MAX_OPERATOR_MESSAGE_BYTES)
        self.sock.setsockopt(zmq.AFFINITY, OPERATOR_IO_AFFINITY)   # an I/O thread of its own (endpoints.py)
        self.sock.setsockopt(zmq.HANDSHAKE_IVL, HANDSHAKE_IVL_MS)  # a connection that never greets is dropped
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
        # open commands, authenticated commands (the loop serves these first), answers
        self._to_loop = {auth: ctx.socket(zmq.PUSH) for auth in (False, True)}
        self._from_loop = ctx.socket(zmq.PULL)
        for auth, sock in self._to_loop.items():
            sock.bind(f"{name}-commands-{int(auth)}")
        self._from_loop.bind(name + "-answers")
        # the event loop's ends: it reads commands from these (authenticated first) and writes answers to the last
        self.loop_commands = []
        for auth in (True, False):
            sock = ctx.socket(zmq.PULL)
            sock.connect(f"{name}-commands-{int(auth)}")
            self.loop_commands.append(sock)
        self.loop_answers = ctx.socket(zmq.PUSH)
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
        for sock in (*self.loop_commands, self.loop_answers):
            sock.close(linger=0)

    def _close_thread_sockets(self) -> None:
        for sock in (*self._to_loop.values(), self._from_loop):
            sock.close(linger=0)
        try:
            self.sock.disable_monitor()   # the resource guard's monitor, if it watches this socket
        except zmq.ZMQError:
            pass
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

    def _receive(self) -> tuple[list[bytes], int, bool] | None:
        """The next waiting message: its first KEEP_FRAMES frames, how many it had, and whether one of them (after
        the identity) is an exact e-stop; None when none waits. libzmq delivers a message whole, so the rest of a
        long one is already here: it is read and dropped frame by frame."""
        try:
            kept = [self.sock.recv(zmq.NOBLOCK)]
        except zmq.Again:
            return None
        count, estop = 1, False
        while self.sock.rcvmore:
            frame = self.sock.recv()
            count += 1
            if len(frame) in _ESTOP_SIZES and frame in ESTOP_FRAMES:
                estop = True
            if len(kept) < KEEP_FRAMES:
                kept.append(frame)
        return kept, count, estop

    def _serve_requests(self) -> int:
        """One turn: read what is waiting, pressing each e-stop and answering each challenge the moment it is read,
        refusing what is over budget unread; then the rest, within the per-connection rate (module docstring).
        Returns how many frames were refused unread."""
        later, dropped, too_long = [], 0, 0
        g = self._global   # all unauthenticated connections' decoding budget, refilled once a turn
        now = time.monotonic()
        g[0] = min(float(OPERATOR_BYTES_BURST), g[0] + (now - g[1]) * OPERATOR_BYTES_RATE)
        g[1] = now
        for _ in range(TURN_REQUESTS):
            received = self._receive()
            if received is None:
                break
            frames, count, estop = received
            route = _route(frames)
            parts, n_parts = frames[len(route):], count - len(route)
            if estop:
                nonce = parts[1] if (n_parts == 2 and parts[0] in ESTOP_FRAMES and len(parts[1]) == NONCE_BYTES) \
                    else None
                self._send_press(route, nonce)
                continue
            if n_parts == 1 and parts[0] in CHALLENGE_FRAMES:
                self._send(route, {"type": P.RESULT, "ok": True, "challenge": self.challenges.issue(now)})
                continue
            if n_parts > MAX_PARTS:   # a multipart bomb's tail was dropped frame by frame above
                too_long += 1
                self._send(route, _TOO_MANY_FRAMES)
                continue
            mac = parts[0] if n_parts == 2 and len(parts[0]) == MAC_BYTES and hmac.compare_digest(
                parts[0], request_mac(self.secret, parts[1])) else None
            if mac is None:
                cost = max(sum(len(p) for p in parts), 64)
                if g[0] < cost:   # the shared budget is spent: a flood; refused unread, the budget untouched
                    dropped += 1
                    self._send(route, _OPERATOR_RATE_LIMITED)
                    continue
                g[0] -= cost
            # the latch's generation as this request is read: a clear_estop among them releases only the latch
            # as it was then, not one pressed by an e-stop read after it in this same turn
            later.append((frames[0], route, parts, mac, self.estop.generation))
        # counted before this turn's requests are handled: a status read among them (a client that got its
        # refusal and asked at once) sees the refusal's counter
        self._count("operator_dropped", dropped)
        self._count("operator_too_many_frames", too_long)
        rate_limited = 0
        for identity, route, parts, mac, generation in later:
            if self._peer_over_rate(identity, now):   # this connection's own limit: told so, unread
                rate_limited += 1
                self._send(route, _OPERATOR_RATE_LIMITED, mac)
                continue
            self._handle(route, *self._decode(parts, mac), mac, now, generation)
        self._count("operator_rate_limited", rate_limited)
        return dropped + too_long + rate_limited

    def _handle(self, route: list[bytes], message: dict | None, refusal: dict | None, mac: bytes | None,
                now: float, generation: int) -> None:
        """One request of the turn, in the order read; ``generation`` is the latch's when it was read."""
        if refusal is not None:
            self._send(route, refusal, mac)
            return
        kind = message["type"]
        if kind == P.OP_ESTOP:   # one that did not look like one (padded, reordered): pressed now
            self._send_press(route, None)
            return
        if kind in PRIVILEGED_COMMANDS:
            code, problem = ERR_UNAUTHORIZED, "needs the operator credential" if mac is None else \
                self._credential_problem()
            if problem is None:
                code, problem = ERR_CHALLENGE, self.challenges.problem(message.get("challenge"), now)
            if problem is not None:
                self._count("operator_unauthorized")
                self._send(route, P.error(code, f"{kind} is the operator's command and {problem} (the operator "
                                                f"credential is {self.secret_file}, readable by the bridge's user "
                                                f"only: run `jepa-robot-bridge {kind.replace('_', '-')}` as that "
                                                "user, or pass --operator-secret FILE); nothing was changed"), mac)
                return
        authenticated = mac is not None
        pending = self._pending[False] + self._pending[True]
        open_full = not authenticated and self._pending[False] >= MAX_PENDING - RESERVED_FOR_OPERATOR
        if pending >= MAX_PENDING or open_full:
            self._count("operator_busy")
            self._send(route, P.error(P.ERR_BUSY, f"{pending} operator commands are waiting for the bridge's event "
                                                  "loop; try again (the e-stop never waits, and the operator's "
                                                  "authenticated commands have places of their own)"), mac)
            return
        if authenticated:
            self.challenges.use(message["challenge"], now)
        nonce = message.get("nonce") if kind == P.OP_STATUS else None
        meta = {"auth": authenticated, "mac": mac,
                "nonce": nonce if type(nonce) is bytes and len(nonce) == NONCE_BYTES else None,
                # the latch's generation when the clear was read: a press read after it keeps the latch
                "generation": generation if kind == P.OP_CLEAR_ESTOP else None}
        self._pending[authenticated] += 1
        self._to_loop[authenticated].send_multipart([*route, msgpack.packb(meta), P.encode(message)])

    def _credential_problem(self) -> str | None:
        """The credential file checked again at each authenticated command: one that became readable by others (or
        another user's, or was removed) since the bridge started is a secret others may hold, for good: privileged
        commands are refused from then on, until the bridge restarts with a new one."""
        if self._compromised is None:
            file = Path(self.secret_file)
            try:
                problem = credential_problem(os.stat(file), file)
            except OSError as exc:
                problem = f"the operator credential {file} is gone ({exc.strerror}); restart the bridge to make one"
            if problem is not None:
                log.error("operator credential: %s", problem)
                self._compromised = (f"{problem} (privileged commands are refused from now on: the secret may have "
                                     "been read; delete the file and restart the bridge, which makes a new one)")
        return self._compromised

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
            meta = msgpack.unpackb(frames[-2])
            self._pending[meta["auth"]] -= 1
            route, payload = frames[:-2], frames[-1]
            if meta["mac"] is not None:
                self._send(route, payload, meta["mac"])
            elif meta["nonce"] is not None:
                self._send_frames(route, [payload, status_proof(self.secret, meta["nonce"], payload)])
            else:
                self._send_frames(route, [payload])

    def _send(self, route: list[bytes], reply: dict | bytes, mac: bytes | None = None) -> None:
        """An answer; to an authenticated request (``mac``) with the proof that this bridge sent it."""
        payload = reply if isinstance(reply, bytes) else encode_reply(reply)
        self._send_frames(route, [payload] if mac is None else [payload, reply_proof(self.secret, mac, payload)])

    def _send_frames(self, route: list[bytes], frames: list[bytes]) -> None:
        try:
            self.sock.send_multipart([*route, *frames], zmq.NOBLOCK)
        except zmq.ZMQError:   # the operator's connection is gone or not reading; nothing is owed
            self._count("undeliverable")

    def _decode(self, parts: list[bytes], mac: bytes | None) -> tuple[dict | None, dict | None]:
        """(message, None) for a known operator command, else (None, the refusal that answers it). ``parts``
        are the request's frames after the route: the message, or its MAC and the message."""
        if len(parts) == 2 and mac is None:
            self._count("operator_unauthorized")
            return None, P.error(ERR_UNAUTHORIZED, "the first frame of this two-frame request is not the MAC of the "
                                                   "second under this bridge's operator credential "
                                                   f"({self.secret_file}); nothing was changed")
        message, refusal = decode_request(parts[-1])
        if refusal is None and message["type"] not in OPERATOR_COMMANDS:
            message, refusal = None, P.error(P.ERR_BAD_MESSAGE, f"unknown operator command {message['type'][:40]!r}; "
                                                                "use estop, clear_estop, confirm, home, status, "
                                                                "shutdown (and challenge before the privileged ones)")
        if refusal is not None:
            self._count("malformed")
        return message, refusal

    def _send_press(self, route: list[bytes], nonce: bytes | None) -> None:
        reply = self._press()
        payload = encode_reply(reply)
        proof = [] if nonce is None else [estop_proof(self.secret, nonce, reply["status"]["held"] is True)]
        self._send_frames(route, [payload, *proof])

    def _press(self) -> dict:
        self._count("estops")
        facts = self.estop.press()
        text = ("the e-stop is latched and the robot was told to hold; the episode ends as interrupted/estop"
                if facts["held"] else "the e-stop is latched (no action is applied) but the backend's stop "
                                      "FAILED: use the hardware e-stop; see the bridge log")
        return {"type": P.RESULT, "ok": True, "status": {**facts, "message": text}}

    def _count(self, name: str, n: int = 1) -> None:
        if n:
            with self._lock:
                self.counters[name] += n

    def counts(self) -> dict:
        with self._lock:
            return dict(self.counters)

    # ------------------------------------------------------------ the event loop's side
    def serve_loop(self, commands: int) -> None:
        """On the event loop: answer up to ``commands`` forwarded commands (the authenticated ones first), and the
        in-process ones."""
        for sock in self.loop_commands:
            while commands > 0:
                try:
                    frames = sock.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                commands -= 1
                meta = msgpack.unpackb(frames[-2])
                message, refusal = decode_request(frames[-1])   # decoded once already: a known, versioned command
                reply = refusal or self._answer(message, meta["generation"])
                self.loop_answers.send_multipart([*frames[:-1], encode_reply(reply)])
        while True:
            try:
                message, generation, box = self._in_process.get_nowait()
            except queue.Empty:
                return
            box.put(self._answer(message, generation))

    def _answer(self, message: dict, generation: int | None) -> dict:
        try:
            return self.answer(message, generation)
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
        generation = self.estop.generation if kind == P.OP_CLEAR_ESTOP else None
        if threading.get_ident() == self.loop_thread:
            return self._answer(message, generation)
        box: queue.Queue = queue.Queue(maxsize=1)
        self._in_process.put((message, generation, box))
        deadline = time.monotonic() + self.command_timeout_s
        while time.monotonic() < deadline and self.loop_thread is not None:
            try:
                return box.get(timeout=0.05)
            except queue.Empty:
                continue
        return P.error(P.ERR_INTERNAL, f"the bridge's event loop did not answer {kind!r} within "
                                       f"{self.command_timeout_s:.1f}s; the e-stop still works (it does not "
                                       "wait for the loop)")
