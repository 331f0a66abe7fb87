"""The robot side of the bridge: one episode's actions, from a validated request through the safety rules to the
backend, and what is recorded of it.

The bridge (``bridge.py``) decides who may ask and when; the runner decides what the robot does with it, top to
bottom: ``reset`` starts an episode; ``run`` executes a synchronous step or chunk, action by action through
``execute`` (the e-stop latch, the ActionGuard's bounds and jump limits, ``backend.apply`` inside the latch's
motion lock, the joint limits), serving the bridge's sockets between two actions
(``between_actions``) so that an e-stop or a lost link stops the chunk at the next action boundary; ``finish``
turns the outcome into the client's reply, or asks the operator to confirm it (``Pending``). The asynchronous
alternative: ``stream`` replaces the queue, ``tick`` runs one action per control period, ``observe`` serves the
newest frames. ``interrupt`` and ``end`` close an episode; ``safety_event`` is the one log of safety events.

Timing (Sec. 4.8): at most ``n_action_steps`` actions per chunk and ``chunk_budget`` chunks
(``chunk_budget * n_action_steps`` actions) per episode; each chunk's frame-to-chunk latency is recorded.
"""
from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from jepa_robot import protocol as P
from jepa_robot.backends.base import RobotBackend, StepResult
from jepa_robot.episodes import EpisodeRecord, FrameHistory, latency_stats
from jepa_robot.estop import EStop
from jepa_robot.safety import ActionGuard, InvalidAction, SafetyConfig, validate_action, validate_chunk
from jepa_robot.streaming import StreamQueue

log = logging.getLogger(__name__)

MAX_HISTORY = 16            # frames an ``observe`` request may ask for


class EStopLatched(RuntimeError):
    """A motion was asked for while the e-stop is latched; nothing moved."""


@dataclass
class Pending:
    """A request whose episode spent its budget: the operator confirms the outcome, then it is answered."""

    reward: float
    reports: list
    executed: int


class EpisodeRunner:
    """Runs the episodes of one backend: its record, frames, jump-limit reference and asynchronous queue."""

    def __init__(self, backend: RobotBackend, safety: SafetyConfig, guard: ActionGuard, estop: EStop,
                 chunk_budget: int, record_dir: str | None, between_actions: Callable[[float], None],
                 apply_estop: Callable[[], None]):
        self.backend, self.safety, self.guard, self.estop = backend, safety, guard, estop
        self.spec = backend.task_spec
        self.period = 1.0 / float(self.spec.control_hz)
        self.chunk_budget = chunk_budget
        self.action_budget = chunk_budget * self.spec.n_action_steps
        self.record_dir = record_dir
        self.between_actions = between_actions   # serves the bridge's sockets (timeout in seconds)
        self.apply_estop = apply_estop           # the bridge's reaction to a latch (interrupt, answer waiters)
        self.episode: EpisodeRecord | None = None
        self.executing = False
        self.abort_reason: str | None = None      # ends the episode (e-stop, watchdog, joint limit ...)
        self.hold_reason: str | None = None       # stops the running chunk only (a held link)
        self.operator_outcome: bool | None = None
        self.prev_action: np.ndarray | None = None
        self.last_command = 0.0
        self.actions_in_chunk = 0
        self.observe_due = False                  # a realtime backend's frame of the last slot is still due
        self.frames = FrameHistory(MAX_HISTORY)
        self.stream = StreamQueue()
        self.events: list[dict] = []   # the bridge's log of safety events (link loss, watchdog, e-stop ...)
        # steady-state frame-to-chunk latencies of all episodes (each episode's first chunk left out, Sec. 4.8)
        self.steady_latencies: collections.deque[float] = collections.deque(maxlen=100_000)
        self.saved_manifests: list[str] = []
        self._summary_key: tuple | None = None
        self._summary: dict = {}

    def latency_summary(self) -> dict:
        """The steady-state frame-to-chunk latencies of all episodes (for ``status``), computed once per new
        chunk: a percentile over 100,000 values takes milliseconds, and operators may ask many times a chunk."""
        key = (len(self.steady_latencies), self.steady_latencies[-1] if self.steady_latencies else None)
        if self._summary_key != key:
            self._summary_key = key
            self._summary = latency_stats(list(self.steady_latencies), skip_first=False)
        return self._summary

    @property
    def running(self) -> bool:
        return self.episode is not None and not self.episode.finished

    def _hold(self) -> None:
        try:
            self.backend.hold()
        except Exception:   # a failing driver call must not stop the loop that guards the robot
            log.exception("backend hold failed")

    # ---------------------------------------------------------------- an episode's start
    def reset(self, seed: int | None, manifest: dict) -> dict:
        """Home the robot (or reset the simulator) and start a recorded episode; the reply with the first frame."""
        if self.running:
            self.end("interrupted", "reset before the episode ended")
        with self.estop.motion("move") as free:   # a press during this homing move stops it concurrently
            if not free:
                return P.error(P.ERR_ESTOP, "the emergency stop is latched; the operator must clear it "
                                            "(jepa-robot-bridge clear-estop) before a new episode")
            obs, info = self.backend.reset(seed)
        if self.estop.latched:   # pressed during the reset (a homing move): it stops here
            self._hold()
        manifest = {**manifest, "seed": seed, "backend": type(self.backend).__name__, "protocol": P.PROTOCOL_VERSION,
                    "safety": self.safety.model_dump(), "action_low": self.guard.low.tolist(),
                    "action_high": self.guard.high.tolist()}
        self.episode = EpisodeRecord(task=self.spec.name, chunk_budget=self.chunk_budget,
                                     action_dim=self.spec.action_dim, manifest=manifest)
        self.episode.add_decision_frame(obs)
        self.operator_outcome = None
        self.prev_action = self.backend.current_action()
        self.actions_in_chunk = 0
        self.stream.reset()
        self.observe_due = False
        self.frames.reset(obs, info)
        self.last_command = self.frames.time
        return {"type": P.RESULT, "obs": obs, "info": self.info(info, [], executed=0)}

    # ---------------------------------------------------------------- synchronous execution
    def run(self, msg: dict, chunk: bool) -> dict | Pending:
        """A ``step`` (one action) or ``chunk`` request: validated whole, then executed action by action."""
        ep = self.episode
        if ep is None:
            return P.error(P.ERR_NO_EPISODE, "no episode has started; call env.reset() first")
        if ep.finished:
            return self.ended_reply()
        if self.stream.active:
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
            self._hold()
            self.safety_event("invalid_action", str(exc))
            self.last_command = time.monotonic()
            return P.error(P.ERR_INVALID_ACTION, f"{exc}; the robot holds position")
        received = time.monotonic()
        if (chunk or self.actions_in_chunk == 0) and ep.chunk_arrived(received - self.frames.time):
            self.steady_latencies.append(received - self.frames.time)
        self.executing, self.abort_reason, self.hold_reason = True, None, None
        reports: list[dict] = []
        total_reward, executed = 0.0, 0
        result: StepResult | None = None
        start = time.monotonic()
        try:
            for i, action in enumerate(actions):
                if self.abort_reason is not None or self.hold_reason is not None:
                    break
                if ep.steps >= self.action_budget:   # the budget counts actions as well as chunks
                    break
                step_result, report, stop = self.execute(action, i)
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
                    self.between_actions(0.0)
                if result.obs is None:
                    result.obs = self.backend.observe()
                self.frames.add(ep.steps, result.obs, result.info)
                if not chunk:
                    self.actions_in_chunk = (self.actions_in_chunk + 1) % self.spec.n_action_steps
                if stop or result.terminated or result.truncated:
                    break
        finally:
            self.executing = False
            self.last_command = time.monotonic()
        if self.abort_reason is not None and not ep.finished:
            self.end("interrupted", self.abort_reason)
        if chunk or self.actions_in_chunk == 0:
            ep.add_decision_frame(self.frames.obs)
        held, self.hold_reason = self.hold_reason, None
        reply = self.finish(result, total_reward, reports, executed)
        if isinstance(reply, dict) and held is not None:
            reply["info"]["held"] = held   # the chunk stopped early on a held link; the episode goes on
        return reply

    def execute(self, action: np.ndarray, index: int) -> tuple[StepResult | None, dict | None, bool]:
        """Check and run one validated action: (result or None when refused, violation report, stop the rest)."""
        ep = self.episode
        if self.estop.latched:
            self.apply_estop()
            return None, None, True   # nothing decided after the latch is applied
        verdict = self.guard.check(action, self.prev_action)
        report = None
        if verdict.violations:
            report = {"index": index, **verdict.report()}
            self.safety_event("refused" if verdict.refused else "clipped", "; ".join(verdict.violations))
        if verdict.refused:
            self._hold()
            ep.add_action(action, None)
            return None, report, True   # later actions assumed this one was reached
        # the latch is checked again where the action starts, under the lock a press takes: a press during the
        # safety check above starts nothing, and one during ``apply`` waits for it, then holds (estop.py)
        with self.estop.motion("action") as free:
            if free:
                result = self.backend.apply(verdict.action)
        if not free:
            self.apply_estop()
            return None, report, True
        if self.estop.latched:   # pressed during a driver call longer than the press waits for: hold after it too
            self._hold()
        self.prev_action = verdict.action
        ep.add_action(action, verdict.action)
        joint_problem = self.guard.joint_violation(self.backend.joint_positions())
        if joint_problem:
            self.safety_event("joint_limit", joint_problem)
            self.interrupt("joint_limit")
            self.abort_reason = self.abort_reason or "joint_limit"
            return result, report, True
        return result, report, False

    def _pace_until(self, deadline: float) -> None:
        """Wait for the next action slot while serving the bridge's sockets (e-stop, link events)."""
        while self.abort_reason is None and self.hold_reason is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self.between_actions(min(remaining, 0.005))

    def finish(self, result: StepResult | None, reward: float, reports: list[dict], executed: int) -> dict | Pending:
        """The reply to an executed request, ending the episode when the simulator, the budget or the operator
        says so; ``Pending`` when the operator must confirm the outcome first (the robot holds meanwhile)."""
        ep = self.episode
        if not ep.finished:
            sim_says_done = result is not None and (result.terminated or result.truncated)
            budget_spent = ep.steps >= self.action_budget or (ep.chunks >= self.chunk_budget
                                                              and self.actions_in_chunk == 0)
            if self.backend.success_source == "sim":
                if sim_says_done or budget_spent:
                    ok = bool(result.info.get("is_success", False)) if result is not None else False
                    self.end("success" if ok else "failure",
                             "simulator ended the episode" if sim_says_done else "chunk budget spent")
            elif self.operator_outcome is not None:
                self.end("success" if self.operator_outcome else "failure", "operator confirmed")
            elif budget_spent or sim_says_done:
                self._hold()
                return Pending(reward, reports, executed)
        terminated = ep.finished and ep.outcome == "success"
        info = self.info(self.frames.info, reports, executed)
        if ep.finished and self.record_dir and self.saved_manifests:
            info["episode_manifest"] = self.saved_manifests[-1]
        return {"type": P.RESULT, "obs": self.frames.obs, "reward": reward, "terminated": terminated,
                "truncated": ep.finished and not terminated, "info": info}

    def ended_reply(self) -> dict:
        ep = self.episode
        return {"type": P.RESULT, "obs": self.frames.obs, "reward": 0.0, "terminated": ep.outcome == "success",
                "truncated": ep.outcome != "success", "info": self.info(self.frames.info, [], executed=0)}

    def info(self, base: dict, reports: list[dict], executed: int) -> dict:
        """The reply's ``info``: the backend's plain values, then the bridge's (safety reports, outcome ...)."""
        ep = self.episode
        info = {k: v for k, v in base.items() if isinstance(v, (bool, int, float, str, np.ndarray, np.generic))}
        info["is_success"] = bool(ep is not None and ep.outcome == "success")
        if self.backend.success_source == "sim" and ep is not None and not ep.finished:
            info["is_success"] = bool(base.get("is_success", False))
        interrupted = ep.reason if ep is not None and ep.outcome == "interrupted" else ""
        info.update(safety=reports, executed=executed, chunks_used=ep.chunks if ep else 0,
                    chunk_budget=self.chunk_budget, estop=self.estop.latched,
                    outcome=ep.outcome if ep else None, interrupted=interrupted)
        return info

    # ---------------------------------------------------------------- asynchronous execution (observe / stream)
    def observe(self, history: int, awaiting: bool) -> dict:
        """The newest ``history`` observations (oldest first; padded with the first frame, as in training)."""
        if not 1 <= history <= MAX_HISTORY:
            raise ValueError(f"history must be an integer in [1, {MAX_HISTORY}]")
        if self.observe_due:
            self._observe_now()
        # observe-only, or no episode yet: the robot as it is now
        frames = self.frames.newest(history) or [(0, time.monotonic(), self.backend.observe())] * history
        ep = self.episode
        info = self.info(self.frames.info, self.stream.take_reports(), executed=0)
        info.update(step=ep.steps if ep is not None else 0, queue=len(self.stream.actions),
                    streaming=self.stream.active, underflow_steps=self.stream.underflow_steps,
                    awaiting_confirmation=awaiting or self.stream.waiting)
        return {"type": P.RESULT, "obs_history": [f[2] for f in frames], "steps": [f[0] for f in frames],
                "info": info}

    def stream_chunk(self, msg: dict) -> dict:
        """A ``stream`` request: the chunk replaces the queue from the step it arrives at."""
        ep = self.episode
        if ep is None:
            return P.error(P.ERR_NO_EPISODE, "no episode has started; call env.reset() first")
        if ep.finished:
            return self.ended_reply()
        origin = msg.get("origin_step")
        if type(origin) is not int or not 0 <= origin <= ep.steps:
            raise ValueError(f"origin_step must be the step of the observation the chunk was predicted from "
                             f"(0..{ep.steps}), got {origin!r:.40}")
        try:
            actions = validate_chunk(msg.get("actions"), self.spec.action_dim, self.backend.rotation6d_starts,
                                     max_actions=self.spec.horizon)
        except InvalidAction as exc:
            self._hold()
            self.stream.actions.clear()
            self.safety_event("invalid_action", str(exc))
            return P.error(P.ERR_INVALID_ACTION, f"{exc}; the queue is emptied and the robot holds")
        now = time.monotonic()
        late = ep.steps - origin    # actions of this chunk whose time has already passed
        origin_time, origin_obs = self.frames.at(origin)
        if ep.chunk_arrived(now - origin_time):
            self.steady_latencies.append(now - origin_time)
        ep.add_decision_frame(origin_obs, step=origin)
        accepted = self.stream.replace(actions, late, now)
        self.last_command = now
        return {"type": P.RESULT, "accepted": accepted, "late_steps": late, "step": ep.steps,
                "underflow_steps": self.stream.underflow_steps}

    def _observe_now(self) -> None:
        self.observe_due = False
        self.frames.add(self.episode.steps, self.backend.observe(), self.frames.info)

    def tick(self, now: float) -> bool:
        """One control period of asynchronous execution: the next queued action, or a counted underflow; True
        when the budget is spent and the operator must now confirm the outcome (the robot holds)."""
        self.stream.tick(now, self.period)
        if self.observe_due:
            self._observe_now()
        if self.episode.steps >= self.action_budget:
            if self.backend.success_source == "sim":
                self.end("success" if self.frames.info.get("is_success") else "failure", "chunk budget spent")
                return False
            self.stream.active, self.stream.waiting = False, True
            self._hold()
            return True
        if not self.stream.actions:
            self.stream.underflow_steps += 1
            self._hold()
            return False
        result, report, stop = self.execute(self.stream.actions.popleft(), index=0)
        if report is not None:
            self.stream.reports.append(report)
        if stop:
            self.stream.actions.clear()
        if result is None:
            return False
        if result.obs is None:
            self.observe_due = True   # the frame of this slot is the one at its end
        else:
            self.frames.add(self.episode.steps, result.obs, result.info)
        if self.abort_reason is not None and self.running:
            self.end("interrupted", self.abort_reason)
        elif result.terminated or result.truncated:
            self.end("success" if result.info.get("is_success") else "failure", "simulator ended the episode")
        self.abort_reason = None
        return False

    # ---------------------------------------------------------------- safety reactions and episode end
    def home(self) -> None:
        """The operator's homing move (it ends a running episode first)."""
        if self.running:
            self.end("interrupted", "homed by the operator")
        with self.estop.motion("move") as free:
            if not free:
                raise EStopLatched("the emergency stop is latched; clear it (jepa-robot-bridge clear-estop) "
                                   "before homing")
            self.backend.home()
        if self.estop.latched:   # pressed during the homing move: it stops here
            self._hold()
        self.prev_action = self.backend.current_action()

    def interrupt(self, reason: str) -> None:
        """Hold position, abort a running chunk at its next action, end the episode as interrupted."""
        self._hold()
        self.stream.actions.clear()
        if self.executing:
            self.abort_reason = self.abort_reason or reason
        if self.running:
            self.end("interrupted", reason)

    def safety_event(self, kind: str, text: str, **extra) -> None:
        event = {"kind": kind, "message": text, "time": time.time(), **extra}
        self.events.append(event)
        del self.events[:-1000]
        log.warning("safety: %s", text)
        if self.running:
            self.episode.add_safety_event(self.episode.steps, {"kind": kind, "message": text})

    def end(self, outcome: str, reason: str) -> None:
        ep = self.episode
        ep.finish(outcome, reason)
        self.stream.stop()
        if self.record_dir:
            try:
                self.saved_manifests.append(str(ep.save(self.record_dir)))
            except Exception as exc:   # a full disk or a bad value: reported, never a reason to stop guarding
                log.exception("episode record failed")
                self.safety_event("record_failed", f"could not write the episode record ({type(exc).__name__}: "
                                                   f"{exc})")
