"""The robot bridge: owns the robot, serves observations, executes actions, enforces the safety rules.

One event-loop thread owns the backend and both ZeroMQ sockets, so no backend call ever races another:

* control socket (ROUTER): the one controlling client (``proxy.RealRobotEnv``) sends hello / reset / step /
  chunk / heartbeat / bye; a second client is refused with ``busy``.
* operator socket (REP): e-stop, clear e-stop, confirm success or failure, home, status, shutdown
  (``OperatorClient`` below, ``jepa-robot-bridge estop|confirm|...`` on the command line).

While a chunk executes, the loop keeps draining both sockets between actions, so an e-stop or a lost link
stops the robot at the next action boundary (at most one control period), not after the chunk.
Timing (Sec. 4.8): actions at ``task_spec.control_hz``, ``n_action_steps`` actions per chunk, a synchronous
loop in which each chunk's frame-to-chunk latency (decision frame produced -> chunk received) is logged.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import secrets
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import zmq

from jepa_envs.real_robot import protocol as P
from jepa_envs.real_robot.backends.base import RobotBackend, StepResult
from jepa_envs.real_robot.episodes import EpisodeRecord, latency_stats
from jepa_envs.real_robot.safety import ActionGuard, InvalidAction, SafetyConfig, validate_action, validate_chunk

log = logging.getLogger(__name__)


@dataclass
class BridgeConfig:
    """Where the bridge listens and what it records."""

    control_address: str = "tcp://127.0.0.1:5555"   # "tcp://127.0.0.1:*" picks a free port
    operator_address: str = "tcp://127.0.0.1:5556"
    record_dir: str | None = None                    # per-episode HDF5 + JSON manifest; None: not written
    chunk_budget: int | None = None                  # None: the task's budget (see ``chunk_budget_for``)


def chunk_budget_for(spec) -> int:
    """The per-task action-chunk budget: real tasks declare it, simulation tasks use their step limit."""
    if "chunk_budget" in spec.extra:
        return int(spec.extra["chunk_budget"])
    return int(math.ceil(spec.max_episode_steps / spec.n_action_steps))


@dataclass
class _Session:
    token: str
    identity: bytes
    client: str
    connected_at: float
    last_seen: float


class RobotBridge:
    """Serve one backend to one controlling client at a time, with safety, watchdog, e-stop and records."""

    def __init__(self, backend: RobotBackend, safety: SafetyConfig | None = None,
                 config: BridgeConfig | None = None,
                 on_confirmation_needed: Callable[[dict], None] | None = None):
        self.backend = backend
        self.spec = backend.task_spec
        self.safety = safety or SafetyConfig()
        self.config = config or BridgeConfig()
        self.guard = ActionGuard(self.safety, backend.action_low, backend.action_high)
        self.period = 1.0 / float(self.spec.control_hz)
        self.link_timeout = self.safety.resolved_link_timeout(self.spec.control_hz)
        self.heartbeat_interval = self.safety.resolved_heartbeat(self.spec.control_hz)
        self.chunk_budget = int(self.config.chunk_budget or chunk_budget_for(self.spec))
        self.on_confirmation_needed = on_confirmation_needed
        self._ctx = zmq.Context()
        self._control: zmq.Socket | None = None
        self._operator: zmq.Socket | None = None
        self._poller = zmq.Poller()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.control_endpoint = ""
        self.operator_endpoint = ""
        # state below is touched only by the event-loop thread
        self._session: _Session | None = None
        self._episode: EpisodeRecord | None = None
        self._estop = False
        self._executing = False
        self._abort_reason: str | None = None
        self._awaiting: tuple[bytes, dict] | None = None
        self._operator_outcome: bool | None = None
        self._prev_action: np.ndarray | None = None
        self._last_command = 0.0
        self._frame_time = 0.0
        self._actions_in_chunk = 0
        self._last_obs: dict | None = None
        self._last_info: dict = {}
        self.events: list[dict] = []   # bridge-level log of safety events (link loss, watchdog, e-stop)
        # steady-state frame-to-chunk latencies of all episodes (each episode's first chunk left out, Sec. 4.8)
        self.steady_latencies: collections.deque[float] = collections.deque(maxlen=100_000)
        self.saved_manifests: list[str] = []

    # ---------------------------------------------------------------- lifecycle
    def bind(self) -> None:
        """Open both sockets; endpoints with port ``*`` resolve to the port actually bound."""
        if self._control is not None:
            return
        self._control = self._ctx.socket(zmq.ROUTER)
        self._control.setsockopt(zmq.LINGER, 0)
        self._control.bind(self.config.control_address)
        self.control_endpoint = self._control.getsockopt_string(zmq.LAST_ENDPOINT)
        self._operator = self._ctx.socket(zmq.REP)
        self._operator.setsockopt(zmq.LINGER, 0)
        self._operator.bind(self.config.operator_address)
        self.operator_endpoint = self._operator.getsockopt_string(zmq.LAST_ENDPOINT)
        self._poller.register(self._control, zmq.POLLIN)
        self._poller.register(self._operator, zmq.POLLIN)

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
        try:
            while not self._stop.is_set():
                self._pump(timeout_s=min(0.01, self.link_timeout / 4))
        finally:
            self.backend.hold()
            if self._episode is not None and not self._episode.finished:
                self._end_episode("interrupted", "bridge stopped")
            for sock in (self._control, self._operator):
                if sock is not None:
                    sock.close(linger=0)
            self._ctx.term()

    # ---------------------------------------------------------------- event pump
    def _pump(self, timeout_s: float) -> None:
        """Handle every pending message, then enforce the timing rules. Called between actions too."""
        events = dict(self._poller.poll(max(0, int(timeout_s * 1000))))
        while events:
            if self._control in events:
                self._on_control(*self._control.recv_multipart())
            if self._operator in events:
                self._on_operator(self._operator.recv())
            events = dict(self._poller.poll(0))
        self._check_timers()

    def _check_timers(self) -> None:
        now = time.monotonic()
        s = self._session
        if s is not None and now - s.last_seen > self.link_timeout:
            self._safety_event("link_lost", f"no message from client {s.client!r} for "
                                            f"{now - s.last_seen:.3f}s (limit {self.link_timeout:.3f}s)",
                               last_seen=s.last_seen, detected=now)
            self._session = None
            self._awaiting = None
            self._interrupt("link_lost")
            return
        if (self._episode_running() and not self._executing and self._awaiting is None
                and now - self._last_command > self.safety.command_deadline_s):
            self._safety_event("watchdog", f"no valid command for {now - self._last_command:.3f}s "
                                           f"(deadline {self.safety.command_deadline_s}s)")
            self._interrupt("watchdog")

    def _episode_running(self) -> bool:
        return self._episode is not None and not self._episode.finished

    def _interrupt(self, reason: str) -> None:
        """Hold position, abort a running chunk at its next action, end the episode as interrupted."""
        self.backend.hold()
        if self._executing:
            self._abort_reason = self._abort_reason or reason
        if self._episode_running():
            self._end_episode("interrupted", reason)

    def _safety_event(self, kind: str, text: str, **extra) -> None:
        event = {"kind": kind, "message": text, "time": time.time(), **extra}
        self.events.append(event)
        log.warning("safety: %s", text)
        if self._episode is not None:
            self._episode.add_safety_event(self._episode.steps, {"kind": kind, "message": text})

    def _end_episode(self, outcome: str, reason: str) -> None:
        ep = self._episode
        ep.finish(outcome, reason)
        if self.config.record_dir:
            self.saved_manifests.append(str(ep.save(self.config.record_dir)))

    # ---------------------------------------------------------------- control socket
    def _send(self, identity: bytes, message: dict) -> None:
        # copy=False: observations are ~150 KB with three 128x128 cameras; let ZeroMQ own the buffer
        self._control.send_multipart([identity, P.encode(message)], copy=False)

    def _on_control(self, identity: bytes, payload: bytes) -> None:
        try:
            msg = P.decode(payload)
            P.check_version(msg)
        except P.ProtocolError as exc:
            code = P.ERR_VERSION if "version" in str(exc) else P.ERR_BAD_MESSAGE
            self._send(identity, P.error(code, str(exc)))
            return
        kind, seq = msg["type"], msg.get("seq")
        if kind == P.HELLO:
            self._send(identity, {**self._on_hello(identity, msg), "seq": seq})
            return
        s = self._session
        if s is None or msg.get("session") != s.token:
            if kind == P.HEARTBEAT:
                return
            holder = f"client {s.client!r}" if s else "no client (reconnect with hello)"
            self._send(identity, {**P.error(P.ERR_NOT_CONTROLLING,
                                            f"this connection does not control the robot; {holder} does"), "seq": seq})
            return
        s.last_seen = time.monotonic()
        if kind == P.HEARTBEAT:
            return
        if self._executing or self._awaiting is not None:
            self._send(identity, {**P.error(P.ERR_BUSY, "a chunk is still executing; wait for its reply"),
                                  "seq": seq})
            return
        handlers = {P.RESET: self._on_reset, P.STEP: self._on_step, P.CHUNK: self._on_chunk,
                    P.RENDER_IMAGES: self._on_render, P.BYE: self._on_bye}
        if kind not in handlers:
            self._send(identity, {**P.error(P.ERR_BAD_MESSAGE, f"unknown message type {kind!r}"), "seq": seq})
            return
        try:
            reply = handlers[kind](identity, msg)
        except Exception as exc:  # a backend or disk failure must not kill the loop that guards the robot
            log.exception("bridge failed to handle %s", kind)
            self._executing = False
            self.backend.hold()
            self._safety_event("internal_error", f"{type(exc).__name__}: {exc}")
            if self._episode_running():
                self._end_episode("interrupted", f"bridge error: {exc}")
            reply = P.error(P.ERR_INTERNAL, f"the bridge failed on {kind!r} ({type(exc).__name__}: {exc}); the "
                                            "robot holds; see the bridge log")
        if reply is not None:
            self._send(identity, {**reply, "seq": seq})

    def describe(self) -> dict:
        """The task and limits a client needs to build its spaces (sent in the welcome message)."""
        spec = dataclasses.asdict(self.spec)
        spec["lowdim"] = [list(x) for x in self.spec.lowdim]
        spec["extra"] = {k: v for k, v in self.spec.extra.items() if isinstance(v, (int, float, str, list, tuple))}
        return {
            "spec": spec,
            "action_low": self.guard.low, "action_high": self.guard.high,
            "control_hz": self.spec.control_hz, "chunk_budget": self.chunk_budget,
            "heartbeat_interval_s": self.heartbeat_interval, "link_timeout_s": self.link_timeout,
            "command_deadline_s": self.safety.command_deadline_s, "on_violation": self.safety.on_violation,
            "success_source": self.backend.success_source, "backend": type(self.backend).__name__,
        }

    def _on_hello(self, identity: bytes, msg: dict) -> dict:
        client = str(msg.get("client") or "anonymous")
        s = self._session
        if s is not None and s.identity != identity:
            return P.error(P.ERR_BUSY, f"the robot is already controlled by client {s.client!r} (connected "
                                       f"{time.monotonic() - s.connected_at:.1f}s ago); only one client may "
                                       "control it: close that client (env.close()) or wait until it disconnects")
        task = msg.get("task")
        if task and task not in (self.spec.name, self.spec.env_id):
            return P.error(P.ERR_TASK, f"this bridge serves task {self.spec.name!r}, the client asked for "
                                       f"{task!r}; start the bridge with --task {task} or connect to the right one")
        now = time.monotonic()
        self._session = _Session(secrets.token_hex(8), identity, client, now, now)
        return {"type": P.WELCOME, "session": self._session.token, "protocol": P.PROTOCOL_VERSION,
                **self.describe()}

    def _on_bye(self, identity: bytes, msg: dict) -> dict:
        if self._episode_running():
            self._interrupt("client closed")
        self._session = None
        return {"type": P.RESULT, "ok": True}

    def _on_render(self, identity: bytes, msg: dict) -> dict:
        self.backend.set_render_images(bool(msg.get("enabled", True)))
        return {"type": P.RESULT, "ok": True}

    def _on_reset(self, identity: bytes, msg: dict) -> dict:
        if self._estop:
            return P.error(P.ERR_ESTOP, "the emergency stop is latched; the operator must clear it "
                                        "(jepa-robot-bridge clear-estop) before a new episode")
        if self._episode_running():
            self._end_episode("interrupted", "reset before the episode ended")
        seed = msg.get("seed")
        obs, info = self.backend.reset(None if seed is None else int(seed))
        manifest = {**dict(msg.get("manifest") or {}), "seed": seed, "backend": type(self.backend).__name__,
                    "protocol": P.PROTOCOL_VERSION, "safety": self.safety.model_dump(),
                    "client": self._session.client}
        self._episode = EpisodeRecord(task=self.spec.name, chunk_budget=self.chunk_budget,
                                      action_dim=self.spec.action_dim, manifest=manifest)
        self._episode.add_decision_frame(obs)
        self._operator_outcome = None
        self._prev_action = self.backend.current_action()
        self._actions_in_chunk = 0
        self._last_obs, self._last_info = obs, info
        self._frame_time = self._last_command = time.monotonic()
        return {"type": P.RESULT, "obs": obs, "info": self._info(info, [], executed=0)}

    def _on_step(self, identity: bytes, msg: dict) -> dict | None:
        return self._run(identity, msg, chunk=False)

    def _on_chunk(self, identity: bytes, msg: dict) -> dict | None:
        return self._run(identity, msg, chunk=True)

    # ---------------------------------------------------------------- execution
    def _ended_reply(self) -> dict:
        ep = self._episode
        info = self._info(self._last_info, [], executed=0)
        return {"type": P.RESULT, "obs": self.backend.observe(), "reward": 0.0,
                "terminated": ep.outcome == "success", "truncated": ep.outcome != "success", "info": info}

    def _info(self, base: dict, reports: list[dict], executed: int) -> dict:
        ep = self._episode
        info = {k: v for k, v in base.items() if isinstance(v, (bool, int, float, str, np.ndarray, np.generic))}
        info["is_success"] = bool(ep is not None and ep.outcome == "success")
        if self.backend.success_source == "sim" and ep is not None and not ep.finished:
            info["is_success"] = bool(base.get("is_success", False))
        interrupted = ep.reason if ep is not None and ep.outcome == "interrupted" else ""
        info.update(safety=reports, executed=executed, chunks_used=ep.chunks if ep else 0,
                    chunk_budget=self.chunk_budget, estop=self._estop, outcome=ep.outcome if ep else None,
                    interrupted=interrupted)
        return info

    def _run(self, identity: bytes, msg: dict, chunk: bool) -> dict | None:
        ep = self._episode
        if ep is None:
            return P.error(P.ERR_NO_EPISODE, "no episode has started; call env.reset() first")
        if ep.finished:
            return self._ended_reply()
        dim = self.spec.action_dim
        try:
            if chunk:
                actions = validate_chunk(msg.get("actions"), dim, self.backend.rotation6d_starts)
            else:
                actions = validate_action(msg.get("action"), dim, self.backend.rotation6d_starts)[None]
        except InvalidAction as exc:
            self.backend.hold()
            self._safety_event("invalid_action", str(exc))
            self._last_command = time.monotonic()
            return P.error(P.ERR_INVALID_ACTION, f"{exc}; the robot holds position")
        received = time.monotonic()
        if chunk or self._actions_in_chunk == 0:
            ep.chunks += 1
            ep.chunk_latency_s.append(received - self._frame_time)
            if ep.chunks > 1:
                self.steady_latencies.append(received - self._frame_time)
        self._executing, self._abort_reason = True, None
        reports: list[dict] = []
        total_reward, executed = 0.0, 0
        result: StepResult | None = None
        start = time.monotonic()
        try:
            for i, action in enumerate(actions):
                if self._abort_reason is not None:
                    break
                verdict = self.guard.check(action, self._prev_action)
                if verdict.violations:
                    reports.append({"index": i, **verdict.report()})
                    self._safety_event("refused" if verdict.refused else "clipped", "; ".join(verdict.violations))
                if verdict.refused:
                    self.backend.hold()
                    ep.add_action(action, None)
                    break   # later actions of the chunk assumed this one was reached
                result = self.backend.apply(verdict.action)
                self._prev_action = verdict.action
                ep.add_action(action, verdict.action)
                executed += 1
                total_reward += result.reward
                if self.backend.realtime:
                    # the slot's frame is the one at its end, after the arm had the period to move
                    self._pace_until(start + (i + 1) * self.period)
                else:
                    self._pump(0)
                if result.obs is None:
                    result.obs = self.backend.observe()
                self._frame_time = time.monotonic()
                self._last_obs, self._last_info = result.obs, result.info
                if not chunk:
                    self._actions_in_chunk = (self._actions_in_chunk + 1) % self.spec.n_action_steps
                joint_problem = self.guard.joint_violation(self.backend.joint_positions())
                if joint_problem:
                    self._safety_event("joint_limit", joint_problem)
                    self._interrupt("joint_limit")
                    break
                if result.terminated or result.truncated:
                    break
        finally:
            self._executing = False
            self._last_command = time.monotonic()
        if self._abort_reason is not None and not ep.finished:
            self._end_episode("interrupted", self._abort_reason)
        if chunk or self._actions_in_chunk == 0:
            ep.add_decision_frame(self._last_obs)
        if self._session is None:
            return None   # the link was lost mid-chunk: nobody to answer
        return self._finish_request(identity, msg, result, total_reward, reports, executed)

    def _pace_until(self, deadline: float) -> None:
        """Wait for the next action slot while serving both sockets (e-stop, heartbeats)."""
        while self._abort_reason is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self._pump(min(remaining, 0.005))

    def _finish_request(self, identity: bytes, msg: dict, result: StepResult | None, reward: float,
                        reports: list[dict], executed: int) -> dict | None:
        ep = self._episode
        terminated = truncated = False
        if not ep.finished:
            sim_says_done = result is not None and (result.terminated or result.truncated)
            budget_spent = ep.chunks >= self.chunk_budget and self._actions_in_chunk == 0
            if self.backend.success_source == "sim":
                if sim_says_done or budget_spent:
                    ok = bool(result.info.get("is_success", False)) if result is not None else False
                    self._end_episode("success" if ok else "failure",
                                      "simulator ended the episode" if sim_says_done else "chunk budget spent")
            elif self._operator_outcome is not None:
                self._end_episode("success" if self._operator_outcome else "failure", "operator confirmed")
            elif budget_spent or sim_says_done:
                pending = {"type": P.RESULT, "reward": reward, "reports": reports, "executed": executed,
                           "seq": msg.get("seq")}
                self._awaiting = (identity, pending)
                self.backend.hold()
                self._send(identity, {"type": P.PENDING, "seq": msg.get("seq"),
                                      "message": "chunk budget spent; waiting for the operator to confirm "
                                                 "success or failure"})
                if self.on_confirmation_needed is not None:
                    self.on_confirmation_needed(ep.summary())
                return None
        if ep.finished:
            terminated = ep.outcome == "success"
            truncated = not terminated
        obs = self._last_obs
        info = self._info(self._last_info, reports, executed)
        if ep.finished and self.config.record_dir and self.saved_manifests:
            info["episode_manifest"] = self.saved_manifests[-1]
        return {"type": P.RESULT, "obs": obs, "reward": reward, "terminated": terminated,
                "truncated": truncated, "info": info}

    # ---------------------------------------------------------------- operator socket
    def _on_operator(self, payload: bytes) -> None:
        try:
            msg = P.decode(payload)
            P.check_version(msg)
            reply = self._operator_command(msg)
        except (P.ProtocolError, ValueError) as exc:
            reply = P.error(P.ERR_BAD_MESSAGE, str(exc))
        self._operator.send(P.encode(reply))

    def _operator_command(self, msg: dict) -> dict:
        kind = msg["type"]
        if kind == P.OP_ESTOP:
            self._estop = True
            self._safety_event("estop", "emergency stop from the operator")
            self._interrupt("estop")
            if self._awaiting is not None:
                identity, pending = self._awaiting
                self._awaiting = None
                self._send(identity, {**self._ended_reply(), "seq": pending["seq"]})
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if kind == P.OP_CLEAR_ESTOP:
            self._estop = False
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if kind == P.OP_CONFIRM:
            return self._confirm(bool(msg.get("success")))
        if kind == P.OP_HOME:
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
        raise ValueError(f"unknown operator command {kind!r}; use estop, clear_estop, confirm, home, status")

    def _confirm(self, success: bool) -> dict:
        if self._awaiting is not None:
            identity, pending = self._awaiting
            self._awaiting = None
            self._end_episode("success" if success else "failure", "operator confirmed")
            reply = self._finish_request(identity, pending, None, pending["reward"], pending["reports"],
                                         pending["executed"])
            self._send(identity, {**reply, "seq": pending["seq"]})
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        if self._episode_running():
            # the goal was reached (or clearly failed) before the budget: the next reply ends the episode
            self._operator_outcome = success
            return {"type": P.RESULT, "ok": True, "status": self.status()}
        return P.error(P.ERR_NO_EPISODE, "no episode is running or waiting for confirmation")

    def status(self) -> dict:
        """A snapshot for operators: controlling client, episode progress, e-stop, latency summary."""
        ep = self._episode
        return {
            "task": self.spec.name,
            "client": self._session.client if self._session else None,
            "estop": self._estop,
            "executing": self._executing,
            "awaiting_confirmation": self._awaiting is not None,
            "episode": None if ep is None else {
                "episode_id": ep.episode_id, "outcome": ep.outcome, "reason": ep.reason, "steps": ep.steps,
                "chunks": ep.chunks, "chunk_budget": self.chunk_budget,
                "frame_to_chunk_latency": latency_stats(ep.chunk_latency_s)},
            "frame_to_chunk_latency_all": latency_stats(list(self.steady_latencies), skip_first=False),
            "events": [dict(e) for e in self.events[-20:]],
        }


class OperatorClient:
    """The operator's side: e-stop, confirm, home, status over the bridge's operator socket."""

    def __init__(self, address: str, timeout_s: float = 5.0):
        self.address = address
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.REQ)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
        self._sock.connect(address)

    def _call(self, message: dict) -> dict:
        self._sock.send(P.encode(message))
        try:
            reply = P.decode(self._sock.recv())
        except zmq.Again as exc:
            raise TimeoutError(f"no robot bridge answered on the operator socket {self.address}; "
                               "is `jepa-robot-bridge serve` running there?") from exc
        if reply["type"] == P.ERROR:
            raise RuntimeError(f"bridge refused {message['type']}: {reply['message']}")
        return reply

    def estop(self) -> dict:
        """Latch the emergency stop: the robot holds now, mid-chunk included; no motion until cleared."""
        return self._call({"type": P.OP_ESTOP})["status"]

    def clear_estop(self) -> dict:
        return self._call({"type": P.OP_CLEAR_ESTOP})["status"]

    def confirm(self, success: bool) -> dict:
        """Confirm the episode's outcome (at budget end, or early when the goal is reached)."""
        return self._call({"type": P.OP_CONFIRM, "success": bool(success)})["status"]

    def home(self) -> dict:
        return self._call({"type": P.OP_HOME})["status"]

    def status(self) -> dict:
        return self._call({"type": P.OP_STATUS})["status"]

    def shutdown(self) -> None:
        self._call({"type": P.OP_SHUTDOWN})

    def close(self) -> None:
        self._sock.close(linger=0)
        self._ctx.term()

    def __enter__(self) -> "OperatorClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
