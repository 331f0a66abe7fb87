"""The robot bridge: owns the robot, serves observations, executes actions, enforces the safety rules.

This file is the flow, top to bottom: the event loop (``_loop`` -> ``_pump``), a control message from its frame
to its handler (``_serve_control`` -> ``_on_control``) and on to the robot (``_on_actions`` ->
``EpisodeRunner.run``, which serves this loop between two actions), the timers (link, watchdog, the
asynchronous queue's ticks), the reaction to a latched e-stop and the operator's commands. Its layers, one
module each:

* ``endpoints.py``: configuration, the loopback rule, CurveZMQ, the control socket.
* ``wire.py``: control frames -> a decoded request (or its refusal), a stranger's limits; replies out.
* ``sessions.py``: who controls the robot (token, seq) and the liveness of that client's link.
* ``estop.py``: the latch, the robot's stop, and the latch across restarts (``supervisor.py`` restarts).
* ``operator_channel.py``: the operator socket in a thread of its own; the e-stop is answered there.
* ``guard.py``: the open connections against the descriptor limit, and the memory: the e-stop latches before
  either runs out.
* ``runner.py``: an episode's actions through the safety rules onto the backend (``streaming.py``: the
  asynchronous queue; ``episodes.py``: the record and the served frames).

One event-loop thread owns the backend and the control socket, so no backend call races another, except the
e-stop's ``emergency_stop`` (the backend's contract). Each loop turn does a bounded amount of work: at most
``IDLE_TURN`` control messages and operator commands (``CHUNK_TURN`` between two actions of a chunk), the
messages taken one per connection in turn by the ROUTER, so no flood delays the session's messages, its
link's echoes or the next action for long.

* control socket (ROUTER): the one controlling client (``proxy.RealRobotEnv``) sends hello / reset / step /
  chunk / observe / stream / bye, and opens its link connection with ``link``; a second client gets ``busy``.
* operator socket (ROUTER, own thread): e-stop, clear e-stop, confirm, home, status, shutdown
  (``jepa_robot.operator.OperatorClient``, ``jepa-robot-bridge estop|confirm|...``; in-process: ``command``).

Timing (Sec. 4.8): actions at ``task_spec.control_hz``, at most ``n_action_steps`` actions per chunk and
``chunk_budget`` chunks (``chunk_budget * n_action_steps`` actions) per episode; each chunk's frame-to-chunk
latency is logged. The asynchronous alternative (``stream``, at most ``horizon`` actions) runs a queue at the
control rate on the bridge's clock; a new chunk replaces what is left of it from the step it arrives at.

Input never stops the bridge: every message is answered with a protocol error or dropped and counted
(``status()["counters"]``). The one liveness rule (docs/real_robot.md, "Lost link and the command watchdog"):
while the link is up, an episode without a command for ``command_deadline_s`` is interrupted (``watchdog``);
once the link is lost the robot holds and the session keeps its episode for ``link_grace_s``; a client back
within it resumes where it was, after it the episode is ``link_lost``.

One module of about 650 lines on purpose: the flow above reads top to bottom in one place, and each of its
layers is a module of its own.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import os
import threading
import time
from typing import Callable

import zmq
from zmq.utils.monitor import parse_monitor_message

from jepa_robot import protocol as P
from jepa_robot.backends.base import RobotBackend
from jepa_robot.operator import CredentialError, ensure_operator_secret

from jepa_robot.endpoints import (IO_THREADS, BridgeConfig, is_loopback, network_bind_problem,
                                            check_rt_priority, open_control_socket, operator_bind_problem,
                                            operator_curve, realtime_context)
from jepa_robot.episodes import check_manifest, latency_stats
from jepa_robot.estop import EStop
from jepa_robot.guard import ResourceGuard
from jepa_robot.operator_channel import OperatorChannel
from jepa_robot.runner import EpisodeRunner, EStopLatched, Pending
from jepa_robot.safety import ActionGuard, SafetyConfig
from jepa_robot.sessions import Refused, SessionKeeper
from jepa_robot.wire import ControlWire, Incoming

log = logging.getLogger(__name__)

IDLE_TURN = (64, 16)        # (control messages, operator commands) served per loop turn ...
CHUNK_TURN = (8, 1)         # ... and between two actions of a chunk
TURN_BUDGET_S = 0.002       # a turn stops reading after this long
DROPPED_PER_MESSAGE = 8     # messages dropped unread (cost: a receive) count this much less than one served
BETWEEN_ACTIONS_S = 0.001   # back-to-back simulated actions serve the sockets at most this often


def chunk_budget_for(spec) -> int:
    """The per-task action-chunk budget: real tasks declare it, simulation tasks use their step limit."""
    if "chunk_budget" in spec.extra:
        return int(spec.extra["chunk_budget"])
    return int(math.ceil(spec.max_episode_steps / spec.n_action_steps))


class RobotBridge:
    """Serve one backend to one controlling client at a time, with safety, watchdog, e-stop and records."""

    def __init__(self, backend: RobotBackend, safety: SafetyConfig | None = None,
                 config: BridgeConfig | None = None,
                 on_confirmation_needed: Callable[[dict], None] | None = None):
        self.backend = backend
        self.spec = backend.task_spec
        self.safety = safety or SafetyConfig()
        self.config = config or BridgeConfig()
        problems = self.safety.problems(self.spec.action_dim, backend.joint_count, self.spec.control_hz,
                                        action_range=(backend.action_low, backend.action_high))
        if problems:
            raise ValueError("the safety configuration does not fit this robot: " + "; ".join(problems))
        bind_problem = (network_bind_problem(self.config.control_address, self.config.curve_secret_key is not None,
                                             self.config.insecure_network)
                        or operator_bind_problem(self.config.operator_address,
                                                 self.config.curve_secret_key is not None))
        if bind_problem:
            raise ValueError(bind_problem)
        self.guard = ActionGuard(self.safety, backend.action_low, backend.action_high)
        self.link_timeout = self.safety.resolved_link_timeout(self.spec.control_hz)
        self.heartbeat_interval = self.safety.resolved_heartbeat(self.spec.control_hz)
        self.link_grace = float(self.safety.link_grace_s)
        self.chunk_budget = int(self.config.chunk_budget or chunk_budget_for(self.spec))
        self.action_budget = self.chunk_budget * self.spec.n_action_steps
        self.on_confirmation_needed = on_confirmation_needed
        # pressed by the operator thread, never waiting for the loop; checked before every action decided
        self.estop = EStop(lambda: self.backend.emergency_stop(), self.config.state_file)
        self.runner = EpisodeRunner(backend, self.safety, self.guard, self.estop, self.chunk_budget,
                                    self.config.record_dir, self._between_actions,
                                    self._apply_estop_if_latched)
        check_rt_priority(self.config.rt_priority)
        self._ctx = zmq.Context(io_threads=IO_THREADS)
        realtime_context(self._ctx, self.config.rt_priority)
        self._auth = None
        self._control: zmq.Socket | None = None
        self._monitor: zmq.Socket | None = None
        self._wire: ControlWire | None = None
        self._operator: OperatorChannel | None = None
        self._guard: ResourceGuard | None = None
        self._poller = zmq.Poller()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.control_endpoint = ""
        self.operator_endpoint = ""
        self.operator_secret_file = ""
        # state below is touched only by the event-loop thread
        self.sessions = SessionKeeper(self.link_timeout, self.link_grace, self.heartbeat_interval)
        self._listening_since = self._turn_end = time.monotonic()
        self._estop_applied = False
        # the client's request that waits for the operator's confirmation: (identity, envelope, seq, Pending)
        self._awaiting: tuple[bytes, list, int, Pending] | None = None
        self.counters: collections.Counter = collections.Counter()   # malformed / replayed / undeliverable ...

    # ---------------------------------------------------------------- lifecycle
    def bind(self) -> None:
        """Restore the e-stop latch, open both sockets; endpoints with port ``*`` resolve to the port bound."""
        if self._control is not None:
            return
        try:
            secret_file, secret = ensure_operator_secret(self.config.operator_secret_file)
        except CredentialError as exc:
            raise ValueError(str(exc)) from None
        try:
            reason = self.estop.restore()
        except OSError as exc:   # a state file it cannot write: the latch would not survive a crash
            raise ValueError(str(exc)) from None
        if reason is None and self.config.start_latched:
            reason = self.config.start_latched
            self.estop.press(reason)
        if reason is not None:
            log.warning("the bridge starts with the e-stop latched: %s", reason)
        try:
            self._control, self._auth = open_control_socket(self._ctx, self.config)
            try:
                self._operator = OperatorChannel(self._ctx, self.config.operator_address, self.estop,
                                                 self._operator_command, lambda: self._guarded(self.backend.hold),
                                                 secret=secret, secret_file=str(secret_file),
                                                 curve=lambda sock: operator_curve(self.config, sock),
                                                 rt_priority=self.config.rt_priority)
            except (zmq.ZMQError, ValueError, OSError):
                if self._auth is not None:
                    self._auth.stop()
                self._control.close(linger=0)
                self._control = None
                raise
        except (zmq.ZMQError, ValueError, OSError, RuntimeError):
            # nothing ran: the state file says so (a latch it held stays), so the next start is not "unclean"
            self.estop.mark_clean_exit()
            raise
        self._wire = ControlWire(self._control, self.counters)
        self.control_endpoint = self._control.getsockopt_string(zmq.LAST_ENDPOINT)
        self.operator_secret_file = str(secret_file)
        self.operator_endpoint = self._operator.endpoint
        # both sockets are watched from here on; the control socket's disconnects come to the loop through it
        self._guard = ResourceGuard(self._ctx, {"control": self._control, "operator": self._operator.sock},
                                    self.estop, self.config.max_rss_mb)
        self._monitor = self._ctx.socket(zmq.PULL)
        self._monitor.setsockopt(zmq.LINGER, 0)
        self._monitor.connect(self._guard.disconnect_address)
        for sock in (self._control, self._monitor, *self._operator.loop_commands):
            self._poller.register(sock, zmq.POLLIN)
        if self.config.curve_secret_key is None and not is_loopback(self.control_endpoint):
            log.warning("the control socket %s is reachable from the network without encryption "
                        "(--insecure-network): anyone who can see the traffic can read the session token",
                        self.control_endpoint)

    def start(self) -> "RobotBridge":
        """Bind and run the event loop in a background thread (tests, bench); returns self."""
        self.bind()
        self._thread = threading.Thread(target=self._loop, name="robot-bridge", daemon=True)
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Bind and run the event loop in the calling thread until ``stop`` or an operator shutdown."""
        self.bind()
        self._loop()

    def stop(self) -> None:
        """Stop the loop, hold the robot, save an unfinished episode, close sockets (not the backend)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None

    def close(self) -> None:
        """Stop and release the backend too."""
        self.stop()
        self.backend.close()

    def __enter__(self) -> "RobotBridge":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _loop(self) -> None:
        self._operator.loop_thread = threading.get_ident()
        self._operator.start()
        self._guard.start()
        try:
            while not self._stop.is_set():
                try:
                    self._pump(self._poll_timeout(), IDLE_TURN)
                except Exception:   # never reached by input (handled per message); a bug must not free the robot
                    self.counters["loop_errors"] += 1
                    log.exception("bridge event loop error; the robot holds")
                    self._guarded(self.backend.hold)
                    time.sleep(0.01)
        finally:   # a stop on purpose (shutdown, SIGINT, SIGTERM); a crash never gets here and restarts latched
            self._operator.loop_thread = None
            self._guarded(self.backend.hold)
            if self.runner.running:
                self.runner.end("interrupted", "bridge stopped")
            self.estop.mark_clean_exit()
            self._operator.stop()
            self._guard.stop()
            try:
                self._control.disable_monitor()
            except zmq.ZMQError:
                pass
            for sock in (self._monitor, self._control):
                sock.close(linger=0)
            if self._auth is not None:
                self._auth.stop()
            self._ctx.term()

    def _poll_timeout(self) -> float:
        timeout = min(0.01, self.heartbeat_interval / 2)
        stream = self.runner.stream
        if stream.active and self.runner.running:
            timeout = min(timeout, max(0.0, stream.next_tick - time.monotonic()))
        return timeout

    @staticmethod
    def _guarded(fn: Callable, *args) -> None:
        try:
            fn(*args)
        except Exception:
            log.exception("backend call %s failed", getattr(fn, "__name__", fn))

    # ---------------------------------------------------------------- event pump
    def _pump(self, timeout_s: float, turn: tuple[int, int]) -> None:
        """One bounded turn between actions: apply a latched e-stop, serve what is waiting, enforce the timers."""
        start = time.monotonic()
        if start - self._turn_end > self.link_timeout / 2:
            # the loop was busy (a long backend call) and could neither ping nor read: silence counts from now
            self._listening_since = start
        self._apply_estop_if_latched()
        events = dict(self._poller.poll(max(0, int(timeout_s * 1000))))
        if self._monitor in events:
            self._serve_monitor()
        if self._control in events:
            self._serve_control(turn[0])
        self._operator.serve_loop(turn[1])
        self._check_timers()
        self._turn_end = time.monotonic()

    def _between_actions(self, timeout_s: float) -> None:
        """The runner's turn between two actions; a simulator's back-to-back actions get one every millisecond
        at most (the sockets wait that long, the robot's actions do not wait for a flood's messages)."""
        if timeout_s > 0 or time.monotonic() - self._turn_end >= BETWEEN_ACTIONS_S:
            self._pump(timeout_s, CHUNK_TURN)

    def _serve_control(self, messages: int) -> None:
        """Up to ``messages`` decoded (or answered) control messages, and up to DROPPED_PER_MESSAGE times as many
        dropped unread (a flood's, or the link's echoes), so the session's requests and its link's echoes, behind
        one message of each connection in the ROUTER's turn, come up within a few turns."""
        deadline = time.monotonic() + TURN_BUDGET_S
        reads = messages * DROPPED_PER_MESSAGE
        while messages > 0 and reads > 0:
            reads -= 1
            now = time.monotonic()
            s = self.sessions.session
            incoming = self._wire.receive(s and s.identity, s and s.link_identity, now)
            if incoming is None:
                return
            resumed = self.sessions.heard(incoming.identity, now)
            if resumed is not None:
                self._link_resumed(resumed)
            self._apply_estop_if_latched()
            if incoming.refusal is not None:
                messages -= 1
                self._wire.send(incoming.identity, incoming.refusal, incoming.envelope)
            elif incoming.message is not None:
                messages -= 1
                self._on_control(incoming)
            if time.monotonic() > deadline:
                return

    def _on_control(self, incoming: Incoming) -> None:
        """One decoded control message: answer strangers without touching state, then the session's request."""
        identity, envelope, msg = incoming.identity, incoming.envelope, incoming.message
        kind, seq = msg["type"], msg.get("seq")
        # 1. a stranger's message (hello from another connection, a wrong token, a stale seq) changes nothing
        try:
            if kind == P.HELLO:
                self._check_task(msg)
                self.sessions.open(identity, msg, incoming.fd, envelope)
                self._reply(identity, envelope, seq, self._welcome())
                return
            if kind == P.LINK:   # the client's link connection: pinged from now on, never answered
                self.sessions.open_link(identity, msg)
                return
            session = self.sessions.authenticate(identity, msg)
        except Refused as refused:
            self.counters[refused.counter] += 1
            if refused.event:
                self.runner.safety_event("replay", refused.event)
            self._wire.send(identity, refused.reply, envelope)
            return
        # 2. the session's own request
        previous_seq = session.last_seq
        resumed = self.sessions.accept(session, identity, seq, incoming.fd, envelope)
        if resumed is not None:
            self._link_resumed(resumed)
        if kind == P.RESUME:
            self._on_resume(identity, envelope, msg, previous_seq)
            return
        handlers = {P.RESET: self._on_reset, P.STEP: self._on_step, P.CHUNK: self._on_chunk,
                    P.OBSERVE: self._on_observe, P.STREAM: self._on_stream,
                    P.RENDER_IMAGES: self._on_render, P.BYE: self._on_bye}
        if kind not in handlers:
            self._reply(identity, envelope, seq, P.error(P.ERR_BAD_MESSAGE, f"unknown message type {kind[:40]!r}"))
            return
        if kind != P.OBSERVE and (self.runner.executing or self._awaiting is not None):
            self._reply(identity, envelope, seq, P.error(P.ERR_BUSY, "a chunk is still executing; wait for its reply"))
            return
        if self.config.observe_only and kind in (P.RESET, P.STEP, P.CHUNK, P.STREAM):
            self._reply(identity, envelope, seq, P.error(
                P.ERR_OBSERVE_ONLY, "this bridge runs observe-only: actions and resets are disabled; restart it "
                                    "without --observe-only to run episodes"))
            return
        try:
            reply = handlers[kind](identity, msg)
        except (P.ProtocolError, TypeError, ValueError, KeyError, OverflowError) as exc:   # a field of the wrong kind
            self.counters["malformed"] += 1
            self._guarded(self.backend.hold)
            reply = P.error(P.ERR_BAD_MESSAGE, f"bad {kind!r} request ({exc}); the robot holds")
        except Exception as exc:  # a backend or disk failure must not kill the loop that guards the robot
            log.exception("bridge failed to handle %s", kind)
            self.counters["internal_errors"] += 1
            self.runner.executing = False
            self._guarded(self.backend.hold)
            self.runner.safety_event("internal_error", f"{type(exc).__name__}: {exc}")
            if self.runner.running:
                self.runner.end("interrupted", f"bridge error: {exc}")
            reply = P.error(P.ERR_INTERNAL, f"the bridge failed on {kind!r} ({type(exc).__name__}: {exc}); the "
                                            "robot holds; see the bridge log")
        if reply is not None:
            self._reply(identity, envelope, seq, reply)

    def _reply(self, identity: bytes, envelope: list, seq, message: dict) -> None:
        """Answer a request; the controlling client's latest reply is kept for a ``resume`` after a reconnect."""
        message = {**message, "seq": seq}
        s = self.sessions.session
        if s is not None and s.identity == identity and message["type"] != P.PENDING:
            s.last_reply = (seq, message)
        self._wire.send(identity, message, envelope)

    # ---------------------------------------------------------------- control requests
    def describe(self) -> dict:
        """The task and limits a client needs to build its spaces (sent in the welcome message)."""
        spec = dataclasses.asdict(self.spec)
        spec["lowdim"] = [list(x) for x in self.spec.lowdim]
        spec["extra"] = {k: v for k, v in self.spec.extra.items() if isinstance(v, (int, float, str, list, tuple))}
        return {
            "spec": spec,
            "action_low": self.guard.low, "action_high": self.guard.high,
            "control_hz": self.spec.control_hz, "chunk_budget": self.chunk_budget,
            "action_budget": self.action_budget, "max_chunk_actions": self.spec.n_action_steps,
            "max_stream_actions": self.spec.horizon,
            "heartbeat_interval_s": self.heartbeat_interval, "link_timeout_s": self.link_timeout,
            "link_grace_s": self.link_grace,
            "command_deadline_s": self.safety.command_deadline_s, "on_violation": self.safety.on_violation,
            "success_source": self.backend.success_source, "backend": type(self.backend).__name__,
            "observe_only": self.config.observe_only,
        }

    def _check_task(self, msg: dict) -> None:
        """A hello may name the task it expects (name or gym id); another one is refused before any session."""
        task = msg.get("task")
        if task is None or (type(task) is str and task in ("", self.spec.name, self.spec.env_id)):
            return
        asked = str(task)[:80] if type(task) is str else f"a {type(task).__name__}"
        raise Refused(P.error(P.ERR_TASK, f"this bridge serves task {self.spec.name!r}, the client asked for "
                                          f"{asked!r}; start the bridge with --task NAME for that task or connect "
                                          "to the right one"), "task_mismatch")

    def _welcome(self) -> dict:
        s = self.sessions.session   # opened just now
        return {"type": P.WELCOME, "session": s.token, "protocol": P.PROTOCOL_VERSION, **self.describe()}

    def _on_resume(self, identity: bytes, envelope: list, msg: dict, previous_seq: int) -> None:
        """A client's connection came back: answer the request it still waits for (``awaiting``: its seq)."""
        s = self.sessions.session
        awaiting = msg.get("awaiting")
        if type(awaiting) is not int:
            self._wire.send(identity, P.error(P.ERR_BAD_MESSAGE, "resume needs 'awaiting': the seq of the request "
                                                                 "whose reply the client still waits for"), envelope)
            return
        if s.last_reply is not None and s.last_reply[0] == awaiting:
            self._wire.send(identity, s.last_reply[1], envelope)   # sent before (maybe into the closed connection)
        elif self._awaiting is not None and self._awaiting[2] == awaiting:
            self._wire.send(identity, {"type": P.PENDING, "seq": awaiting, "message": "still waiting for the "
                                       "operator to confirm success or failure"}, envelope)
        elif awaiting > previous_seq:   # the request itself never arrived
            self._wire.send(identity, {**P.error(P.ERR_LOST, f"request {awaiting} never reached the bridge (the "
                                                             "connection dropped first); nothing of it was executed; "
                                                             "send it again"), "seq": awaiting}, envelope)
        # else: the request arrived and its reply is still being made; it goes to the new connection

    def _on_bye(self, identity: bytes, msg: dict) -> dict:
        if self.runner.running:
            self.runner.interrupt("client closed")
        self.sessions.close()
        return {"type": P.RESULT, "ok": True}

    def _on_render(self, identity: bytes, msg: dict) -> dict:
        self.backend.set_render_images(P.field(msg, "enabled", bool, True))
        return {"type": P.RESULT, "ok": True}

    def _on_reset(self, identity: bytes, msg: dict) -> dict:
        if self.estop.latched:
            return P.error(P.ERR_ESTOP, "the emergency stop is latched; the operator must clear it "
                                        "(jepa-robot-bridge clear-estop) before a new episode")
        seed = msg.get("seed")
        if seed is not None and (type(seed) is not int or not 0 <= seed < 2**63):
            raise ValueError(f"seed must be a non-negative integer or null, got {seed!r:.40}")
        # checked before anything moves: the episode's record must be able to hold it (JSON)
        manifest = check_manifest(msg.get("manifest") or {})
        return self.runner.reset(seed, {**manifest, "client": self.sessions.session.client})

    def _on_step(self, identity: bytes, msg: dict) -> dict | None:
        return self._on_actions(identity, msg, chunk=False)

    def _on_chunk(self, identity: bytes, msg: dict) -> dict | None:
        return self._on_actions(identity, msg, chunk=True)

    def _on_actions(self, identity: bytes, msg: dict, chunk: bool) -> dict | None:
        reply = self.runner.run(msg, chunk)   # serves the sockets between actions (e-stop, link, strangers)
        if self.sessions.session is None:
            return None   # control was released meanwhile: nobody to answer
        if isinstance(reply, Pending):   # the budget is spent: the operator decides, the robot holds meanwhile
            s = self.sessions.session
            self._awaiting = (identity, s.envelope, msg.get("seq"), reply)
            self._wire.send(identity, {"type": P.PENDING, "seq": msg.get("seq"), "message": "chunk budget spent; "
                                       "waiting for the operator to confirm success or failure"}, s.envelope)
            self._confirmation_needed()
            return None
        return reply

    def _on_observe(self, identity: bytes, msg: dict) -> dict:
        return self.runner.observe(P.field(msg, "history", int, 1), awaiting=self._awaiting is not None)

    def _on_stream(self, identity: bytes, msg: dict) -> dict:
        return self.runner.stream_chunk(msg)

    def _confirmation_needed(self) -> None:
        if self.on_confirmation_needed is not None:
            self.on_confirmation_needed(self.runner.episode.summary())

    # ---------------------------------------------------------------- timers: link, watchdog, streaming
    def _serve_monitor(self) -> None:
        event = parse_monitor_message(self._monitor.recv_multipart())
        if event["event"] != zmq.EVENT_DISCONNECTED:
            return
        s = self.sessions.session
        if self.sessions.disconnected(event["value"]):
            self._link_hold("closed", "the client's control connection closed (its process ended, or the network "
                                      "dropped it)")
        elif s is not None and not s.held and s.fd is None and not self._wire.send(
                s.identity, {"type": P.LINK, "state": "probe"}, s.envelope):
            self._link_hold("closed", "the client's control connection closed")

    def _check_timers(self) -> None:
        now = time.monotonic()
        ping = self.sessions.ping_due(now)
        if ping is not None and not self._wire.send(ping.link_identity, {"type": P.LINK, "state": "ping"},
                                                    count=False) and not ping.held:
            self._link_hold("closed", "the client's link connection is gone")
        probe = self.sessions.probe_due(now)
        if probe is not None and not self._wire.send(probe.identity, {"type": P.LINK, "state": "up"}, probe.envelope,
                                                     count=False):
            # backstop for a closed connection whose event was missed (it closed before its last message was
            # read, or this libzmq reports no descriptors): a notice to a connection that is gone fails at once
            self._link_hold("closed", "the client's control connection is gone")
        if self.sessions.silent(now, self._listening_since):
            self._link_hold("silent", f"nothing from the client for {self.link_timeout:.3f}s (no request and no echo "
                                      "of the bridge's pings on its link connection)")
        if self.sessions.grace_over(now):
            self._link_lost(now)
        run, s = self.runner, self.sessions.session
        link_up = s is not None and not s.held   # a held session is governed by the grace, not the watchdog
        idle = not run.executing and self._awaiting is None and not run.stream.waiting
        if run.running and link_up and idle and now - run.last_command > self.safety.command_deadline_s:
            run.safety_event("watchdog", f"no valid command for {now - run.last_command:.3f}s "
                                         f"(deadline {self.safety.command_deadline_s}s)")
            run.interrupt("watchdog")
        if (run.stream.active or run.stream.waiting) and run.running:
            if run.operator_outcome is not None:
                run.end("success" if run.operator_outcome else "failure", "operator confirmed")
            elif run.stream.active and now >= run.stream.next_tick:
                if run.executing or self._awaiting is not None or not link_up:
                    run.stream.next_tick = now + run.period
                elif run.tick(now):
                    self._confirmation_needed()

    def _link_hold(self, cause: str, why: str) -> None:
        s = self.sessions.hold(cause)
        self._guarded(self.backend.hold)
        self.runner.stream.actions.clear()
        if self.runner.executing:
            self.runner.hold_reason = "link_hold"
        self.runner.safety_event("link_hold", f"link to client {s.client!r} lost: {why}; the robot holds and the "
                                              f"session is kept for {self.link_grace:.1f}s")

    def _link_resumed(self, held_s: float) -> None:
        self.runner.last_command = time.monotonic()   # the watchdog counts from the resume, not from the hold
        self.runner.safety_event("link_resumed", f"client {self.sessions.session.client!r} back after "
                                                 f"{held_s:.3f}s; control resumes")

    def _link_lost(self, now: float) -> None:
        s, held = self.sessions.drop(now)
        self.runner.safety_event("link_lost", f"no connection from client {s.client!r} for {held:.3f}s "
                                              f"(grace {self.link_grace:.1f}s); control released",
                                 held_since=s.held_since, detected=now)
        self._awaiting = None
        self.runner.interrupt("link_lost")

    def _apply_estop_if_latched(self) -> bool:
        """Act on a latch the operator thread set (and on which it already stopped the robot): hold, interrupt
        the episode, answer a client waiting for confirmation."""
        if not self.estop.latched or self._estop_applied:
            return False
        self._estop_applied = True
        self.runner.safety_event("estop", self.estop.reason or "emergency stop from the operator")
        self.runner.interrupt("estop")
        if self._awaiting is not None:
            identity, envelope, seq, _ = self._awaiting
            self._awaiting = None
            self._reply(identity, envelope, seq, self.runner.ended_reply())
        return True

    # ---------------------------------------------------------------- operator commands (on the event loop)
    def command(self, message: dict) -> dict:
        """Run an operator command (``{"type": "confirm", "success": True}`` ...) from any thread of this process;
        the e-stop latches in the calling thread, as on the operator socket."""
        return self._operator.handle(message)

    def _operator_command(self, msg: dict, generation: int | None = None) -> dict:
        """One operator command on the event loop; ``generation``: the latch's when a clear_estop arrived."""
        kind = msg["type"]
        if kind == P.OP_CLEAR_ESTOP:
            if not self.estop.clear(generation):
                return P.error(P.ERR_PRESSED_SINCE, "the e-stop was pressed again after this clear_estop reached the "
                                                    "bridge; it stays latched: check the robot and the scene, then "
                                                    "clear again")
            self._estop_applied = False
        elif kind == P.OP_CONFIRM:
            success = msg.get("success")
            if type(success) is not bool:
                raise ValueError("confirm needs 'success': true or false")
            if self._awaiting is not None:
                identity, envelope, seq, pending = self._awaiting
                self._awaiting = None
                self.runner.end("success" if success else "failure", "operator confirmed")
                self._reply(identity, envelope, seq, self.runner.finish(None, pending.reward, pending.reports,
                                                                        pending.executed))
            elif self.runner.running:
                # the goal was reached (or clearly failed) before the budget: the next reply ends the episode
                self.runner.operator_outcome = success
            else:
                return P.error(P.ERR_NO_EPISODE, "no episode is running or waiting for confirmation")
        elif kind == P.OP_HOME:
            if self.config.observe_only:
                return P.error(P.ERR_OBSERVE_ONLY, "this bridge runs observe-only: it never moves the robot")
            if self.estop.latched:
                return P.error(P.ERR_ESTOP, "the emergency stop is latched; clear it (jepa-robot-bridge "
                                            "clear-estop) before homing")
            if self.runner.executing:
                return P.error(P.ERR_BUSY, "a chunk is executing; e-stop first or wait for it to finish")
            try:
                self.runner.home()
            except EStopLatched as exc:   # pressed between the check above and the move: nothing moved
                return P.error(P.ERR_ESTOP, str(exc))
        elif kind == P.OP_SHUTDOWN:
            self._stop.set()
            return {"type": P.RESULT, "ok": True}
        elif kind != P.OP_STATUS:
            raise ValueError(f"unknown operator command {str(kind)[:40]!r}; use estop, clear_estop, confirm, home, "
                             "status, shutdown")
        return {"type": P.RESULT, "ok": True, "status": self.status()}

    def status(self) -> dict:
        """A snapshot for operators: controlling client, episode progress, e-stop, latency summary, process id."""
        run, ep, s = self.runner, self.runner.episode, self.sessions.session
        counters = collections.Counter(self.counters)
        if self._operator is not None:
            counters.update(self._operator.counts())
        if self._guard is not None:
            counters.update(self._guard.counts())
        return {
            "task": self.spec.name, "pid": os.getpid(), "observe_only": self.config.observe_only,
            "client": s.client if s else None, "link": None if s is None else ("held" if s.held else "up"),
            "estop": self.estop.latched, "estop_reason": self.estop.reason,
            "executing": run.executing, "streaming": run.stream.active,
            "awaiting_confirmation": self._awaiting is not None,
            "episode": None if ep is None else {
                "episode_id": ep.episode_id, "outcome": ep.outcome, "reason": ep.reason, "steps": ep.steps,
                "chunks": ep.chunks, "chunk_budget": self.chunk_budget, "action_budget": self.action_budget,
                "underflow_steps": run.stream.underflow_steps,
                "frame_to_chunk_latency": latency_stats(ep.chunk_latency_s)},
            "frame_to_chunk_latency_all": run.latency_summary(),
            "counters": dict(counters),
            "resources": None if self._guard is None else self._guard.facts(),
            "events": [dict(e) for e in run.events[-20:]],
        }
