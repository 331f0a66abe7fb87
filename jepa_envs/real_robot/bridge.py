"""The robot bridge: owns the robot, serves observations, executes actions, enforces the safety rules.

Layers, one file each:

* ``wire.py``: control-socket frames -> a decoded request (or the refusal that answers it); replies out.
* ``sessions.py``: who controls the robot (token, seq) and the liveness of that client's link.
* ``operator_channel.py``: the operator socket in a thread of its own; the e-stop latches there.
* ``episodes.py``: the per-episode record and its files.
* this file: the event loop, and the flow from a received frame to an applied action.

One event-loop thread owns the backend and the control socket, so no backend call ever races another. The
flow of a control message, top to bottom in this file: ``_pump`` (the latched e-stop is applied first, before
any byte is decoded) -> ``_serve_control`` (``wire.receive``) -> ``_on_control``: a stranger's message (no
session, a wrong token, a stale seq) is answered and counted and touches nothing; the session's own request
goes to its handler -> ``_run`` (a synchronous step or chunk) -> ``_execute`` (the latch, then the
ActionGuard's bounds and jump limits, then ``backend.apply``, then the joint limits).

* control socket (ROUTER): the one controlling client (``proxy.RealRobotEnv``) sends hello / reset / step /
  chunk / observe / stream / bye; a second client is refused with ``busy``.
* operator socket (REP, own thread): e-stop, clear e-stop, confirm success or failure, home, status, shutdown
  (``jepa_operator.OperatorClient``, ``jepa-robot-bridge estop|confirm|...``); the same commands from inside
  the bridge's process go through ``RobotBridge.command``.

While a chunk executes, the loop keeps draining the control socket and the operator's commands between
actions, so an e-stop or a lost link stops the robot at the next action boundary (at most one control period).
Timing (Sec. 4.8): actions at ``task_spec.control_hz``, at most ``n_action_steps`` actions per chunk and
``chunk_budget`` chunks (``chunk_budget * n_action_steps`` actions) per episode, a synchronous loop in which
each chunk's frame-to-chunk latency (decision frame produced -> chunk received) is logged. The asynchronous
alternative (``stream``, at most ``horizon`` actions) executes a queue at the control rate on the bridge's
clock while the client infers the next chunk, which replaces what is left of the queue from the step it
arrives at.

Input never stops the bridge: every message, of any framing, payload and field types, is answered with a
protocol error or dropped and counted (``status()["counters"]``).

Liveness and the command watchdog, one rule (docs/real_robot.md, "Lost link and the command watchdog"): while
the session's link is up, an episode without a command for ``command_deadline_s`` is interrupted (``watchdog``);
once the link is lost the robot holds and the session keeps its episode for ``link_grace_s`` (the watchdog does
not run while it is held); a client back within the grace resumes where it was, after it the episode is
``link_lost``.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import zmq
from zmq.utils.monitor import parse_monitor_message

from jepa_envs.real_robot import protocol as P
from jepa_envs.real_robot.backends.base import RobotBackend, StepResult
from jepa_envs.real_robot.episodes import EpisodeRecord, check_manifest, latency_stats
from jepa_envs.real_robot.operator_channel import OperatorChannel
from jepa_envs.real_robot.safety import ActionGuard, InvalidAction, SafetyConfig, validate_action, validate_chunk
from jepa_envs.real_robot.sessions import Refused, SessionKeeper
from jepa_envs.real_robot.wire import ControlWire, Incoming

log = logging.getLogger(__name__)

MAX_HISTORY = 16            # frames an ``observe`` request may ask for


@dataclass
class BridgeConfig:
    """Where the bridge listens and what it records."""

    control_address: str = "tcp://127.0.0.1:5555"   # "tcp://127.0.0.1:*" picks a free port
    operator_address: str = "tcp://127.0.0.1:5556"
    record_dir: str | None = None                    # per-episode HDF5 + JSON manifest; None: not written
    chunk_budget: int | None = None                  # None: the task's budget (see ``chunk_budget_for``)
    observe_only: bool = False                       # serve observations; refuse every motion
    curve_secret_key: str | None = None              # CurveZMQ: the bridge's key file (jepa-robot-bridge keys)
    curve_authorized_dir: str | None = None          # CurveZMQ: public keys of the clients allowed to connect
    insecure_network: bool = False                   # allow a network bind without CurveZMQ (said explicitly)


def chunk_budget_for(spec) -> int:
    """The per-task action-chunk budget: real tasks declare it, simulation tasks use their step limit."""
    if "chunk_budget" in spec.extra:
        return int(spec.extra["chunk_budget"])
    return int(math.ceil(spec.max_episode_steps / spec.n_action_steps))


def is_loopback(endpoint: str) -> bool:
    """Whether a ZeroMQ endpoint is reachable from this computer only."""
    host = endpoint.split("://", 1)[-1].rsplit(":", 1)[0]
    return endpoint.startswith(("inproc://", "ipc://")) or P.is_loopback_host(host)


def network_bind_problem(control_address: str, curve: bool, insecure_network: bool) -> str | None:
    """Why a control socket may not bind here: a network address without CurveZMQ, unless said explicitly."""
    if curve or insecure_network or is_loopback(control_address):
        return None
    return (f"the control socket {control_address} would be reachable from the network without encryption: "
            "anyone who can reach it can read the session token and drive the robot; use CurveZMQ "
            "(--curve-keys, or curve_secret_key/curve_authorized_dir in the set-up file), bind 127.0.0.1 and "
            "tunnel over SSH, or pass --insecure-network on a dedicated, isolated robot-policy link "
            "(docs/real_robot.md, 'Network security')")


class RobotBridge:
    """Serve one backend to one controlling client at a time, with safety, watchdog, e-stop and records."""

    def __init__(self, backend: RobotBackend, safety: SafetyConfig | None = None,
                 config: BridgeConfig | None = None,
                 on_confirmation_needed: Callable[[dict], None] | None = None):
        self.backend = backend
        self.spec = backend.task_spec
        self.safety = safety or SafetyConfig()
        self.config = config or BridgeConfig()
        problems = self.safety.problems(self.spec.action_dim, backend.joint_count, self.spec.control_hz)
        if problems:
            raise ValueError("the safety configuration does not fit this robot: " + "; ".join(problems))
        bind_problem = network_bind_problem(self.config.control_address, self.config.curve_secret_key is not None,
                                            self.config.insecure_network)
        if bind_problem:
            raise ValueError(bind_problem)
        self.guard = ActionGuard(self.safety, backend.action_low, backend.action_high)
        self.period = 1.0 / float(self.spec.control_hz)
        self.link_timeout = self.safety.resolved_link_timeout(self.spec.control_hz)
        self.heartbeat_interval = self.safety.resolved_heartbeat(self.spec.control_hz)
        self.link_grace = float(self.safety.link_grace_s)
        self.chunk_budget = int(self.config.chunk_budget or chunk_budget_for(self.spec))
        self.action_budget = self.chunk_budget * self.spec.n_action_steps
        self.on_confirmation_needed = on_confirmation_needed
        self._ctx = zmq.Context()
        self._auth = None
        self._control: zmq.Socket | None = None
        self._monitor: zmq.Socket | None = None
        self._wire: ControlWire | None = None
        self._operator: OperatorChannel | None = None
        self._poller = zmq.Poller()
        self._thread: threading.Thread | None = None
        self._loop_thread_id: int | None = None
        self._loop_running = False
        self._stop = threading.Event()
        self._commands: queue.Queue = queue.Queue()
        # set by the operator thread before the loop sees anything; checked before any decode and every action
        self.estop_latch = threading.Event()
        self.control_endpoint = ""
        self.operator_endpoint = ""
        # state below is touched only by the event-loop thread
        self.sessions = SessionKeeper(self.link_timeout, self.link_grace)
        self._episode: EpisodeRecord | None = None
        self._estop_applied = False
        self._executing = False
        self._abort_reason: str | None = None         # ends the episode (e-stop, watchdog, joint limit ...)
        self._hold_reason: str | None = None          # stops the running chunk only (a held link)
        self._awaiting: tuple[bytes, dict] | None = None
        self._operator_outcome: bool | None = None
        self._prev_action: np.ndarray | None = None
        self._last_command = 0.0
        self._frame_time = 0.0
        self._actions_in_chunk = 0
        self._last_obs: dict | None = None
        self._last_info: dict = {}
        self._recent: collections.deque = collections.deque(maxlen=MAX_HISTORY)   # (step, time, obs)
        # asynchronous execution (``stream``)
        self._streaming = False
        self._queue: collections.deque = collections.deque()
        self._next_tick = 0.0
        self._observe_due = False
        self._underflow_steps = 0
        self._stream_waiting = False   # stream budget spent: the operator confirms the outcome
        self._stream_reports: list[dict] = []
        self.events: list[dict] = []   # bridge-level log of safety events (link loss, watchdog, e-stop)
        self.counters: collections.Counter = collections.Counter()   # malformed / replayed / undeliverable ...
        # steady-state frame-to-chunk latencies of all episodes (each episode's first chunk left out, Sec. 4.8)
        self.steady_latencies: collections.deque[float] = collections.deque(maxlen=100_000)
        self.saved_manifests: list[str] = []

    # ---------------------------------------------------------------- lifecycle
    def bind(self) -> None:
        """Open both sockets; endpoints with port ``*`` resolve to the port actually bound."""
        if self._control is not None:
            return
        control = self._ctx.socket(zmq.ROUTER)
        control.setsockopt(zmq.LINGER, 0)
        control.setsockopt(zmq.ROUTER_MANDATORY, 1)      # a reply to a vanished client fails instead of vanishing
        control.setsockopt(zmq.MAXMSGSIZE, P.MAX_CONTROL_MESSAGE_BYTES)
        control.setsockopt(zmq.HEARTBEAT_IVL, max(1, round(self.heartbeat_interval * 1000)))
        control.setsockopt(zmq.HEARTBEAT_TIMEOUT, max(1, round(self.link_timeout * 1000)))
        self._setup_curve(control)
        control.bind(self.config.control_address)
        self._control = control
        self._wire = ControlWire(control, self.counters)
        self.control_endpoint = control.getsockopt_string(zmq.LAST_ENDPOINT)
        self._monitor = control.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        self._operator = OperatorChannel(self._ctx, self.config.operator_address, self.estop_latch,
                                         self._call_loop)
        self.operator_endpoint = self._operator.endpoint
        for sock in (self._control, self._monitor):
            self._poller.register(sock, zmq.POLLIN)
        if self.config.curve_secret_key is None and not is_loopback(self.control_endpoint):
            log.warning("the control socket %s is reachable from the network without encryption "
                        "(--insecure-network): anyone who can see the traffic can read the session token",
                        self.control_endpoint)

    def _setup_curve(self, sock: zmq.Socket) -> None:
        if self.config.curve_secret_key is None:
            return
        import zmq.auth
        from zmq.auth.thread import ThreadAuthenticator

        if not zmq.has("curve"):
            raise RuntimeError("this libzmq has no CURVE support; install pyzmq's wheels (they include it)")
        public, secret = zmq.auth.load_certificate(self.config.curve_secret_key)
        if secret is None:
            raise ValueError(f"{self.config.curve_secret_key} holds no secret key; pass the bridge's "
                             "'.key_secret' file made by `jepa-robot-bridge keys`")
        authorized = self.config.curve_authorized_dir
        if not authorized or not Path(authorized).is_dir():
            raise ValueError("CurveZMQ needs curve_authorized_dir: a folder with the public key of every client "
                             "allowed to connect (`jepa-robot-bridge keys` writes one)")
        self._auth = ThreadAuthenticator(self._ctx)
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(authorized))
        sock.curve_secretkey, sock.curve_publickey, sock.curve_server = secret, public, True

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
        self._loop_thread_id = threading.get_ident()
        self._loop_running = True
        self._operator.start()
        try:
            while not self._stop.is_set():
                try:
                    self._pump(timeout_s=self._poll_timeout())
                except Exception:   # never reached by input (handled per message); a bug must not free the robot
                    self.counters["loop_errors"] += 1
                    log.exception("bridge event loop error; the robot holds")
                    self._guarded(self.backend.hold)
                    time.sleep(0.01)
        finally:
            self._loop_running = False
            self._guarded(self.backend.hold)
            if self._episode_running():
                self._end_episode("interrupted", "bridge stopped")
            self._operator.stop()
            if self._control is not None:
                try:
                    self._control.disable_monitor()
                except zmq.ZMQError:
                    pass
            for sock in (self._monitor, self._control):
                if sock is not None:
                    sock.close(linger=0)
            if self._auth is not None:
                self._auth.stop()
            self._ctx.term()

    def _poll_timeout(self) -> float:
        timeout = min(0.01, self.link_timeout / 4)
        if self._streaming and self._episode_running():
            timeout = min(timeout, max(0.0, self._next_tick - time.monotonic()))
        return timeout

    @staticmethod
    def _guarded(fn: Callable, *args) -> None:
        try:
            fn(*args)
        except Exception:
            log.exception("backend call %s failed", getattr(fn, "__name__", fn))

    # ---------------------------------------------------------------- event pump
    def _pump(self, timeout_s: float) -> None:
        """Apply a latched e-stop, handle every pending message, enforce the timing rules. Runs between actions."""
        self._apply_estop_if_latched()
        events = dict(self._poller.poll(max(0, int(timeout_s * 1000))))
        while events:
            if self._monitor in events:
                self._serve_monitor()
            self._apply_estop_if_latched()
            if self._control in events:
                self._serve_control()
            events = dict(self._poller.poll(0))
        self._serve_commands()
        self._check_timers()

    def _serve_control(self) -> None:
        incoming = self._wire.receive()
        if incoming.refusal is not None:
            self._wire.send(incoming.identity, incoming.refusal, incoming.envelope)
            return
        self._on_control(incoming)

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
            session = self.sessions.authenticate(identity, msg)
        except Refused as refused:
            self.counters[refused.counter] += 1
            if refused.event:
                self._safety_event("replay", refused.event)
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
        if kind != P.OBSERVE and (self._executing or self._awaiting is not None):
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
            self._executing = False
            self._guarded(self.backend.hold)
            self._safety_event("internal_error", f"{type(exc).__name__}: {exc}")
            if self._episode_running():
                self._end_episode("interrupted", f"bridge error: {exc}")
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
        elif self._awaiting is not None and self._awaiting[1]["seq"] == awaiting:
            self._wire.send(identity, {"type": P.PENDING, "seq": awaiting, "message": "still waiting for the "
                                       "operator to confirm success or failure"}, envelope)
        elif awaiting > previous_seq:   # the request itself never arrived
            self._wire.send(identity, {**P.error(P.ERR_LOST, f"request {awaiting} never reached the bridge (the "
                                                             "connection dropped first); nothing of it was executed; "
                                                             "send it again"), "seq": awaiting}, envelope)
        # else: the request arrived and its reply is still being made; it goes to the new connection

    def _on_bye(self, identity: bytes, msg: dict) -> dict:
        if self._episode_running():
            self._interrupt("client closed")
        self.sessions.close()
        return {"type": P.RESULT, "ok": True}

    def _on_render(self, identity: bytes, msg: dict) -> dict:
        self.backend.set_render_images(P.field(msg, "enabled", bool, True))
        return {"type": P.RESULT, "ok": True}

    def _on_reset(self, identity: bytes, msg: dict) -> dict:
        if self.estop_latch.is_set():
            return P.error(P.ERR_ESTOP, "the emergency stop is latched; the operator must clear it "
                                        "(jepa-robot-bridge clear-estop) before a new episode")
        seed = msg.get("seed")
        if seed is not None and (type(seed) is not int or not 0 <= seed < 2**63):
            raise ValueError(f"seed must be a non-negative integer or null, got {seed!r:.40}")
        # checked before anything moves: the episode's record must be able to hold it (JSON)
        manifest = check_manifest(msg.get("manifest") or {})
        if self._episode_running():
            self._end_episode("interrupted", "reset before the episode ended")
        obs, info = self.backend.reset(seed)
        manifest = {**manifest, "seed": seed, "backend": type(self.backend).__name__,
                    "protocol": P.PROTOCOL_VERSION, "safety": self.safety.model_dump(),
                    "action_low": self.guard.low.tolist(), "action_high": self.guard.high.tolist(),
                    "client": self.sessions.session.client}
        self._episode = EpisodeRecord(task=self.spec.name, chunk_budget=self.chunk_budget,
                                      action_dim=self.spec.action_dim, manifest=manifest)
        self._episode.add_decision_frame(obs)
        self._operator_outcome = None
        self._prev_action = self.backend.current_action()
        self._actions_in_chunk = 0
        self._streaming, self._stream_waiting, self._observe_due, self._underflow_steps = False, False, False, 0
        self._queue.clear()
        self._stream_reports = []
        self._last_obs, self._last_info = obs, info
        self._frame_time = self._last_command = time.monotonic()
        self._recent.clear()
        self._recent.append((0, self._frame_time, obs))
        return {"type": P.RESULT, "obs": obs, "info": self._info(info, [], executed=0)}

    def _on_step(self, identity: bytes, msg: dict) -> dict | None:
        return self._run(identity, msg, chunk=False)

    def _on_chunk(self, identity: bytes, msg: dict) -> dict | None:
        return self._run(identity, msg, chunk=True)

    # ---------------------------------------------------------------- synchronous execution
    def _run(self, identity: bytes, msg: dict, chunk: bool) -> dict | None:
        ep = self._episode
        if ep is None:
            return P.error(P.ERR_NO_EPISODE, "no episode has started; call env.reset() first")
        if ep.finished:
            return self._ended_reply()
        if self._streaming:
            return P.error(P.ERR_BAD_MESSAGE, "this episode streams its actions; send stream messages, or reset "
                                              "to run it with step / chunk")
        dim = self.spec.action_dim
        try:
            if chunk:
                actions = validate_chunk(msg.get("actions"), dim, self.backend.rotation6d_starts,
                                         max_actions=self.spec.n_action_steps)
            else:
                actions = validate_action(msg.get("action"), dim, self.backend.rotation6d_starts)[None]
        except InvalidAction as exc:
            self._guarded(self.backend.hold)
            self._safety_event("invalid_action", str(exc))
            self._last_command = time.monotonic()
            return P.error(P.ERR_INVALID_ACTION, f"{exc}; the robot holds position")
        received = time.monotonic()
        if chunk or self._actions_in_chunk == 0:
            ep.chunks += 1
            ep.chunk_latency_s.append(received - self._frame_time)
            if ep.chunks > 1:
                self.steady_latencies.append(received - self._frame_time)
        self._executing, self._abort_reason, self._hold_reason = True, None, None
        reports: list[dict] = []
        total_reward, executed = 0.0, 0
        result: StepResult | None = None
        start = time.monotonic()
        try:
            for i, action in enumerate(actions):
                if self._abort_reason is not None or self._hold_reason is not None:
                    break
                if ep.steps >= self.action_budget:   # the budget counts actions as well as chunks
                    break
                step_result, report, stop = self._execute(action, i)
                if report is not None:
                    reports.append(report)
                if step_result is None:
                    break
                result = step_result
                executed += 1
                total_reward += result.reward
                if self.backend.realtime:
                    # the slot's frame is the one at its end, after the arm had the period to move
                    self._pace_until(start + (i + 1) * self.period)
                else:
                    self._pump(0)
                if result.obs is None:
                    result.obs = self.backend.observe()
                self._set_frame(result.obs, result.info)
                if not chunk:
                    self._actions_in_chunk = (self._actions_in_chunk + 1) % self.spec.n_action_steps
                if stop or result.terminated or result.truncated:
                    break
        finally:
            self._executing = False
            self._last_command = time.monotonic()
        if self._abort_reason is not None and not ep.finished:
            self._end_episode("interrupted", self._abort_reason)
        if chunk or self._actions_in_chunk == 0:
            ep.add_decision_frame(self._last_obs)
        held, self._hold_reason = self._hold_reason, None
        if self.sessions.session is None:
            return None   # control was released meanwhile: nobody to answer
        reply = self._finish_request(identity, msg, result, total_reward, reports, executed)
        if reply is not None and held is not None:
            reply["info"]["held"] = held   # the chunk stopped early on a held link; the episode goes on
        return reply

    def _execute(self, action: np.ndarray, index: int) -> tuple[StepResult | None, dict | None, bool]:
        """Check and run one validated action: (result or None when refused, violation report, stop the rest)."""
        ep = self._episode
        self._apply_estop_if_latched()
        if self.estop_latch.is_set():
            return None, None, True   # latched since the last check: nothing more is applied
        verdict = self.guard.check(action, self._prev_action)
        report = None
        if verdict.violations:
            report = {"index": index, **verdict.report()}
            self._safety_event("refused" if verdict.refused else "clipped", "; ".join(verdict.violations))
        if verdict.refused:
            self._guarded(self.backend.hold)
            ep.add_action(action, None)
            return None, report, True   # later actions assumed this one was reached
        result = self.backend.apply(verdict.action)
        self._prev_action = verdict.action
        ep.add_action(action, verdict.action)
        joint_problem = self.guard.joint_violation(self.backend.joint_positions())
        if joint_problem:
            self._safety_event("joint_limit", joint_problem)
            self._interrupt("joint_limit")
            self._abort_reason = self._abort_reason or "joint_limit"
            return result, report, True
        return result, report, False

    def _pace_until(self, deadline: float) -> None:
        """Wait for the next action slot while serving the control socket and the operator (e-stop, link events)."""
        while self._abort_reason is None and self._hold_reason is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self._pump(min(remaining, 0.005))

    def _ended_reply(self) -> dict:
        ep = self._episode
        info = self._info(self._last_info, [], executed=0)
        return {"type": P.RESULT, "obs": self._last_obs, "reward": 0.0,
                "terminated": ep.outcome == "success", "truncated": ep.outcome != "success", "info": info}

    def _info(self, base: dict, reports: list[dict], executed: int) -> dict:
        ep = self._episode
        info = {k: v for k, v in base.items() if isinstance(v, (bool, int, float, str, np.ndarray, np.generic))}
        info["is_success"] = bool(ep is not None and ep.outcome == "success")
        if self.backend.success_source == "sim" and ep is not None and not ep.finished:
            info["is_success"] = bool(base.get("is_success", False))
        interrupted = ep.reason if ep is not None and ep.outcome == "interrupted" else ""
        info.update(safety=reports, executed=executed, chunks_used=ep.chunks if ep else 0,
                    chunk_budget=self.chunk_budget, estop=self.estop_latch.is_set(),
                    outcome=ep.outcome if ep else None, interrupted=interrupted)
        return info

    def _budget_spent(self) -> bool:
        ep = self._episode
        return ep.steps >= self.action_budget or (ep.chunks >= self.chunk_budget and self._actions_in_chunk == 0)

    def _finish_request(self, identity: bytes, msg: dict, result: StepResult | None, reward: float,
                        reports: list[dict], executed: int) -> dict | None:
        ep = self._episode
        if not ep.finished:
            sim_says_done = result is not None and (result.terminated or result.truncated)
            budget_spent = self._budget_spent()
            if self.backend.success_source == "sim":
                if sim_says_done or budget_spent:
                    ok = bool(result.info.get("is_success", False)) if result is not None else False
                    self._end_episode("success" if ok else "failure",
                                      "simulator ended the episode" if sim_says_done else "chunk budget spent")
            elif self._operator_outcome is not None:
                self._end_episode("success" if self._operator_outcome else "failure", "operator confirmed")
            elif budget_spent or sim_says_done:
                s = self.sessions.session
                envelope = s.envelope if s is not None else []
                pending = {"type": P.RESULT, "reward": reward, "reports": reports, "executed": executed,
                           "seq": msg.get("seq"), "envelope": envelope}
                self._awaiting = (identity, pending)
                self._guarded(self.backend.hold)
                self._wire.send(identity, {"type": P.PENDING, "seq": msg.get("seq"),
                                           "message": "chunk budget spent; waiting for the operator to confirm "
                                                      "success or failure"}, envelope)
                if self.on_confirmation_needed is not None:
                    self.on_confirmation_needed(ep.summary())
                return None
        terminated = ep.finished and ep.outcome == "success"
        truncated = ep.finished and not terminated
        info = self._info(self._last_info, reports, executed)
        if ep.finished and self.config.record_dir and self.saved_manifests:
            info["episode_manifest"] = self.saved_manifests[-1]
        return {"type": P.RESULT, "obs": self._last_obs, "reward": reward, "terminated": terminated,
                "truncated": truncated, "info": info}

    # ---------------------------------------------------------------- asynchronous execution (observe / stream)
    def _on_observe(self, identity: bytes, msg: dict) -> dict:
        """The newest ``history`` observations (oldest first; padded with the first frame, as in training)."""
        history = P.field(msg, "history", int, 1)
        if not 1 <= history <= MAX_HISTORY:
            raise ValueError(f"history must be an integer in [1, {MAX_HISTORY}]")
        if self._observe_due:
            self._observe_now()
        if self._recent:
            frames = list(self._recent)[-history:]
        else:   # observe-only, or no episode yet: the robot as it is now
            frames = [(0, time.monotonic(), self.backend.observe())]
        frames = [frames[0]] * (history - len(frames)) + frames
        ep = self._episode
        reports, self._stream_reports = self._stream_reports, []
        info = self._info(self._last_info, reports, executed=0)
        info.update(step=ep.steps if ep is not None else 0, queue=len(self._queue), streaming=self._streaming,
                    underflow_steps=self._underflow_steps,
                    awaiting_confirmation=self._awaiting is not None or self._stream_waiting)
        return {"type": P.RESULT, "obs_history": [f[2] for f in frames], "steps": [f[0] for f in frames],
                "info": info}

    def _on_stream(self, identity: bytes, msg: dict) -> dict:
        ep = self._episode
        if ep is None:
            return P.error(P.ERR_NO_EPISODE, "no episode has started; call env.reset() first")
        if ep.finished:
            return self._ended_reply()
        origin = msg.get("origin_step")
        if type(origin) is not int or not 0 <= origin <= ep.steps:
            raise ValueError(f"origin_step must be the step of the observation the chunk was predicted from "
                             f"(0..{ep.steps}), got {origin!r:.40}")
        try:
            actions = validate_chunk(msg.get("actions"), self.spec.action_dim, self.backend.rotation6d_starts,
                                     max_actions=self.spec.horizon)
        except InvalidAction as exc:
            self._guarded(self.backend.hold)
            self._queue.clear()
            self._safety_event("invalid_action", str(exc))
            return P.error(P.ERR_INVALID_ACTION, f"{exc}; the queue is emptied and the robot holds")
        now = time.monotonic()
        late = ep.steps - origin    # actions of this chunk whose time has already passed
        origin_time = next((t for step, t, _ in reversed(self._recent) if step == origin), self._frame_time)
        origin_obs = next((o for step, _, o in reversed(self._recent) if step == origin), self._last_obs)
        ep.chunks += 1
        ep.chunk_latency_s.append(now - origin_time)
        if ep.chunks > 1:
            self.steady_latencies.append(now - origin_time)
        ep.add_decision_frame(origin_obs, step=origin)
        self._queue = collections.deque(actions[late:])   # real-time chunking: replaces what is left
        if not self._streaming:
            self._streaming, self._next_tick = True, now
        self._last_command = now
        return {"type": P.RESULT, "accepted": len(self._queue), "late_steps": late, "step": ep.steps,
                "underflow_steps": self._underflow_steps}

    def _observe_now(self) -> None:
        self._observe_due = False
        obs = self.backend.observe()
        self._set_frame(obs, self._last_info)

    def _set_frame(self, obs: dict, info: dict) -> None:
        self._frame_time = time.monotonic()
        self._last_obs, self._last_info = obs, info
        self._recent.append((self._episode.steps, self._frame_time, obs))

    def _stream_tick(self, now: float) -> None:
        """One control period of asynchronous execution: the next queued action, or a counted underflow."""
        s = self.sessions.session
        if self._executing or self._awaiting is not None or s is None or s.held:
            self._next_tick = now + self.period
            return
        self._next_tick = max(self._next_tick + self.period, now)   # never bursts to catch up
        if self._observe_due:
            self._observe_now()
        if self._episode.steps >= self.action_budget:
            if self.backend.success_source == "sim":
                self._end_episode("success" if self._last_info.get("is_success") else "failure",
                                  "chunk budget spent")
            else:   # the operator decides; the robot holds meanwhile
                self._streaming, self._stream_waiting = False, True
                self._guarded(self.backend.hold)
                if self.on_confirmation_needed is not None:
                    self.on_confirmation_needed(self._episode.summary())
            return
        if not self._queue:
            self._underflow_steps += 1
            self._guarded(self.backend.hold)
            return
        result, report, stop = self._execute(self._queue.popleft(), index=0)
        if report is not None:
            self._stream_reports.append(report)
        if stop:
            self._queue.clear()
        if result is None:
            return
        if result.obs is None:
            self._observe_due = True   # the frame of this slot is the one at its end
        else:
            self._set_frame(result.obs, result.info)
        if self._abort_reason is not None and self._episode_running():
            self._end_episode("interrupted", self._abort_reason)
        elif result.terminated or result.truncated:
            self._end_episode("success" if result.info.get("is_success") else "failure",
                              "simulator ended the episode")
        self._abort_reason = None

    # ---------------------------------------------------------------- timers: link, watchdog, streaming
    def _serve_monitor(self) -> None:
        event = parse_monitor_message(self._monitor.recv_multipart())
        if event["event"] != zmq.EVENT_DISCONNECTED:
            return
        s = self.sessions.session
        if self.sessions.disconnected(event["value"]):
            self._link_hold("the client's connection closed (process ended, or no heartbeat answer for "
                            f"{self.link_timeout:.3f}s)")
        elif s is not None and not s.held and s.fd is None and not self._wire.send(
                s.identity, {"type": P.LINK, "state": "probe"}, s.envelope):
            self._link_hold("the client's connection closed")

    def _check_timers(self) -> None:
        now = time.monotonic()
        probe = self.sessions.probe_due(now)
        if probe is not None and not self._wire.send(probe.identity, {"type": P.LINK, "state": "up"}, probe.envelope,
                                                     count=False):
            # backstop for a closed connection whose event was missed (it closed before its last message was
            # read, or this libzmq reports no descriptors): a notice to a connection that is gone fails at once
            self._link_hold("the client's connection is gone")
        if self.sessions.grace_over(now):
            self._link_lost(now)
        s = self.sessions.session
        link_up = s is not None and not s.held   # a held session is governed by the grace, not the watchdog
        if (self._episode_running() and link_up and not self._executing and self._awaiting is None
                and not self._stream_waiting and now - self._last_command > self.safety.command_deadline_s):
            self._safety_event("watchdog", f"no valid command for {now - self._last_command:.3f}s "
                                           f"(deadline {self.safety.command_deadline_s}s)")
            self._interrupt("watchdog")
        if (self._streaming or self._stream_waiting) and self._episode_running():
            if self._operator_outcome is not None:
                self._end_episode("success" if self._operator_outcome else "failure", "operator confirmed")
            elif self._streaming and now >= self._next_tick:
                self._stream_tick(now)

    def _link_hold(self, why: str) -> None:
        s = self.sessions.hold()
        self._guarded(self.backend.hold)
        self._queue.clear()
        if self._executing:
            self._hold_reason = "link_hold"
        self._safety_event("link_hold", f"link to client {s.client!r} lost: {why}; the robot holds and the "
                                        f"session is kept for {self.link_grace:.1f}s")

    def _link_resumed(self, held_s: float) -> None:
        self._last_command = time.monotonic()   # the watchdog counts from the resume, not from before the hold
        self._safety_event("link_resumed", f"client {self.sessions.session.client!r} back after {held_s:.3f}s; "
                                           "control resumes")

    def _link_lost(self, now: float) -> None:
        s, held = self.sessions.drop(now)
        self._safety_event("link_lost", f"no connection from client {s.client!r} for {held:.3f}s "
                                        f"(grace {self.link_grace:.1f}s); control released",
                           held_since=s.held_since, detected=now)
        self._awaiting = None
        self._interrupt("link_lost")

    # ---------------------------------------------------------------- safety reactions and episode end
    def _episode_running(self) -> bool:
        return self._episode is not None and not self._episode.finished

    def _interrupt(self, reason: str) -> None:
        """Hold position, abort a running chunk at its next action, end the episode as interrupted."""
        self._guarded(self.backend.hold)
        self._queue.clear()
        if self._executing:
            self._abort_reason = self._abort_reason or reason
        if self._episode_running():
            self._end_episode("interrupted", reason)

    def _apply_estop_if_latched(self) -> bool:
        """Act on a latch the operator thread set: hold, interrupt, answer a client waiting for confirmation."""
        if not self.estop_latch.is_set() or self._estop_applied:
            return False
        self._estop_applied = True
        self._safety_event("estop", "emergency stop from the operator")
        self._interrupt("estop")
        if self._awaiting is not None:
            identity, pending = self._awaiting
            self._awaiting = None
            self._reply(identity, pending["envelope"], pending["seq"], self._ended_reply())
        return True

    def _safety_event(self, kind: str, text: str, **extra) -> None:
        event = {"kind": kind, "message": text, "time": time.time(), **extra}
        self.events.append(event)
        del self.events[:-1000]
        log.warning("safety: %s", text)
        if self._episode is not None and not self._episode.finished:
            self._episode.add_safety_event(self._episode.steps, {"kind": kind, "message": text})

    def _end_episode(self, outcome: str, reason: str) -> None:
        ep = self._episode
        ep.finish(outcome, reason)
        self._streaming = self._stream_waiting = False
        self._queue.clear()
        if self.config.record_dir:
            try:
                self.saved_manifests.append(str(ep.save(self.config.record_dir)))
            except Exception as exc:   # a full disk or a bad value: reported, never a reason to stop guarding
                log.exception("episode record failed")
                self._safety_event("record_failed", f"could not write the episode record "
                                                    f"({type(exc).__name__}: {exc})")

    # ---------------------------------------------------------------- operator commands (on the event loop)
    def command(self, message: dict) -> dict:
        """Run an operator command (``{"type": "confirm", "success": True}`` ...) from any thread of this process;
        the e-stop latches before the event loop is asked, as on the operator socket."""
        return self._operator.handle(message)

    def _call_loop(self, message: dict, timeout_s: float) -> dict:
        """Run ``message`` on the event loop (which owns the robot) and wait for its answer; TimeoutError if the
        loop does not answer in time."""
        if threading.get_ident() == self._loop_thread_id:
            return self._answer_operator(message)
        box: queue.Queue = queue.Queue(maxsize=1)
        self._commands.put((message, box))
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return box.get(timeout=min(0.05, max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                if not self._loop_running or time.monotonic() >= deadline:
                    raise TimeoutError("the bridge's event loop did not answer") from None

    def _serve_commands(self) -> None:
        while True:
            try:
                message, reply_box = self._commands.get_nowait()
            except queue.Empty:
                return
            reply_box.put(self._answer_operator(message))

    def _answer_operator(self, msg: dict) -> dict:
        try:
            return self._operator_command(msg)
        except (P.ProtocolError, ValueError, TypeError) as exc:
            self.counters["malformed"] += 1
            return P.error(P.ERR_BAD_MESSAGE, str(exc))
        except Exception as exc:
            self.counters["internal_errors"] += 1
            log.exception("operator command failed")
            self._guarded(self.backend.hold)
            return P.error(P.ERR_INTERNAL, f"the bridge failed on this command ({type(exc).__name__}: {exc}); "
                                           "the robot holds")

    def _operator_command(self, msg: dict) -> dict:
        kind = msg["type"]
        if kind == P.OP_ESTOP:
            self._apply_estop_if_latched()
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if kind == P.OP_CLEAR_ESTOP:
            self.estop_latch.clear()
            self._estop_applied = False
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if kind == P.OP_CONFIRM:
            success = msg.get("success")
            if type(success) is not bool:
                raise ValueError("confirm needs 'success': true or false")
            return self._confirm(success)
        if kind == P.OP_HOME:
            if self.config.observe_only:
                return P.error(P.ERR_OBSERVE_ONLY, "this bridge runs observe-only: it never moves the robot")
            if self.estop_latch.is_set():
                return P.error(P.ERR_ESTOP, "the emergency stop is latched; clear it (jepa-robot-bridge "
                                            "clear-estop) before homing")
            if self._executing:
                return P.error(P.ERR_BUSY, "a chunk is executing; e-stop first or wait for it to finish")
            if self._episode_running():
                self._end_episode("interrupted", "homed by the operator")
            self.backend.home()
            self._prev_action = self.backend.current_action()
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if kind == P.OP_STATUS:
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if kind == P.OP_SHUTDOWN:
            self._stop.set()
            return {"type": P.RESULT, "ok": True}
        raise ValueError(f"unknown operator command {str(kind)[:40]!r}; use estop, clear_estop, confirm, home, "
                         "status, shutdown")

    def _confirm(self, success: bool) -> dict:
        if self._awaiting is not None:
            identity, pending = self._awaiting
            self._awaiting = None
            self._end_episode("success" if success else "failure", "operator confirmed")
            reply = self._finish_request(identity, pending, None, pending["reward"], pending["reports"],
                                         pending["executed"])
            self._reply(identity, pending["envelope"], pending["seq"], reply)
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if self._episode_running():
            # the goal was reached (or clearly failed) before the budget: the next reply ends the episode
            self._operator_outcome = success
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        return P.error(P.ERR_NO_EPISODE, "no episode is running or waiting for confirmation")

    def status(self) -> dict:
        """A snapshot for operators: controlling client, episode progress, e-stop, latency summary."""
        ep = self._episode
        s = self.sessions.session
        counters = collections.Counter(self.counters)
        if self._operator is not None:
            counters.update(self._operator.counts())
        return {
            "task": self.spec.name,
            "client": s.client if s else None,
            "link": None if s is None else ("held" if s.held else "up"),
            "estop": self.estop_latch.is_set(),
            "observe_only": self.config.observe_only,
            "executing": self._executing,
            "streaming": self._streaming,
            "awaiting_confirmation": self._awaiting is not None,
            "episode": None if ep is None else {
                "episode_id": ep.episode_id, "outcome": ep.outcome, "reason": ep.reason, "steps": ep.steps,
                "chunks": ep.chunks, "chunk_budget": self.chunk_budget, "action_budget": self.action_budget,
                "underflow_steps": self._underflow_steps,
                "frame_to_chunk_latency": latency_stats(ep.chunk_latency_s)},
            "frame_to_chunk_latency_all": latency_stats(list(self.steady_latencies), skip_first=False),
            "counters": dict(counters),
            "events": [dict(e) for e in self.events[-20:]],
        }
