"""Asynchronous chunk execution (real-time chunking) beside the paper's synchronous loop.

Synchronous (Sec. 4.8, ``RealRobotEnv.step_chunk``): observe, infer, execute the chunk, observe again; the robot
waits while the policy thinks. Asynchronous (this module): the bridge executes a queue of actions on its own
clock while the policy infers the next chunk from a newer observation. A chunk predicted from the observation of
step ``o`` plans actions for steps ``o, o+1, ...``; when it reaches the bridge at step ``s`` its first ``s - o``
actions are already in the past (the inference latency, converted to steps by the bridge's own step counter)
and are dropped, and the rest replaces whatever was left of the queue. Each executed action is therefore the
one its chunk planned for that very step. If a chunk arrives after the queue ran dry, the robot holds for those
periods and the bridge counts them (``underflow_steps``).

``policy_fn(frames) -> (H, A) actions`` receives the newest ``history`` observations, oldest first (padded with
the first frame at the start of an episode, as in training).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class AsyncEpisode:
    """What one asynchronous episode did: per decision, when and how late; the bridge's outcome."""

    seed: int | None
    outcome: str | None = None
    is_success: bool = False
    interrupted: str = ""
    steps: int = 0
    underflow_steps: int = 0
    decisions: list[dict] = field(default_factory=list)

    def summary(self) -> dict:
        latency = np.asarray([d["inference_s"] for d in self.decisions], np.float64)
        late = np.asarray([d["late_steps"] for d in self.decisions], np.int64)
        return {"seed": self.seed, "outcome": self.outcome, "is_success": self.is_success,
                "interrupted": self.interrupted, "steps": self.steps, "decisions": len(self.decisions),
                "underflow_steps": self.underflow_steps,
                "inference_ms_median": float(np.median(latency) * 1e3) if latency.size else None,
                "late_steps_median": float(np.median(late)) if late.size else None,
                "late_steps_max": int(late.max()) if late.size else None}


class AsyncChunkExecutor:
    """Run episodes on a bridge with asynchronous execution: infer while the previous chunk executes."""

    def __init__(self, env, policy_fn: Callable[[list[dict]], np.ndarray], history: int = 1,
                 replan_steps: int | None = None, confirmation_timeout_s: float = 900.0):
        self.env = env.unwrapped if hasattr(env, "unwrapped") else env
        self.policy_fn = policy_fn
        self.history = int(history)
        spec = self.env.task_spec
        self.period = 1.0 / float(spec.control_hz)
        # replan once this many actions of the current chunk have run (default: half the synchronous chunk)
        self.replan_steps = int(replan_steps or max(1, spec.n_action_steps // 2))
        if self.replan_steps < 1:
            raise ValueError("replan_steps must be >= 1")
        self.confirmation_timeout_s = float(confirmation_timeout_s)

    def run_episode(self, seed: int | None = None, manifest: dict | None = None) -> AsyncEpisode:
        env = self.env
        env.reset(seed=seed, options={"manifest": {**(manifest or {}), "execution": "async",
                                                   "replan_steps": self.replan_steps}})
        record = AsyncEpisode(seed)
        frames, info = env.observe(self.history)
        while info["outcome"] is None and not info.get("awaiting_confirmation"):
            origin = int(info["step"])
            start = time.monotonic()
            chunk = np.asarray(self.policy_fn(frames), np.float64)
            inference = time.monotonic() - start
            reply = env.stream(chunk, origin)
            record.decisions.append({"origin_step": origin, "inference_s": inference,
                                     "latency_steps": math.ceil(inference / self.period - 1e-9),
                                     "late_steps": int(reply.get("late_steps", 0)),
                                     "accepted": int(reply.get("accepted", 0))})
            if "accepted" not in reply:   # the episode ended meanwhile: the reply is the final result
                break
            # wait until ``replan_steps`` actions of this chunk have run, then look again
            due = origin + self.replan_steps
            time.sleep(max(0.0, (due - int(reply["step"])) * self.period))
            frames, info = env.observe(self.history)
            while info["outcome"] is None and int(info["step"]) < due and not info.get("awaiting_confirmation"):
                time.sleep(self.period / 4)
                frames, info = env.observe(self.history)
        deadline = time.monotonic() + self.confirmation_timeout_s
        while info["outcome"] is None and time.monotonic() < deadline:   # the operator confirms the outcome
            time.sleep(0.1)
            frames, info = env.observe(self.history)
        record.outcome, record.is_success = info["outcome"], bool(info["is_success"])
        record.interrupted, record.steps = info.get("interrupted", ""), int(info.get("step", 0))
        record.underflow_steps = int(info.get("underflow_steps", 0))
        return record
