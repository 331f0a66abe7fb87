"""The policy side: a Gymnasium env whose robot lives behind a robot bridge.

``gym.make("JEPA/RealRobot-v0", task="Cabinet", address="tcp://robot-pc:5555")`` gives the same observation
and action conventions as the simulated envs (a Dict of ``<camera>_image`` uint8 and float32 low-dim keys,
absolute actions, ``info["is_success"]``). For the real robot ``is_success`` is the operator's confirmation
at episode end. ``step_chunk`` sends a whole action chunk in one round trip (the paper's synchronous loop,
Sec. 4.8). A background thread heartbeats on its own socket so the bridge notices a dead policy process
within one control period.
"""
from __future__ import annotations

import dataclasses
import os
import socket
import threading
import time

import numpy as np
import zmq
from gymnasium import spaces

from jepa_envs.base import JEPAEnv
from jepa_envs.real_robot import protocol as P
from jepa_envs.spec import TaskSpec


class BridgeError(RuntimeError):
    """The bridge refused a request; ``code`` is the protocol's error code."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


class BridgeBusy(BridgeError):
    """Another client already controls the robot."""


class ActionRefused(BridgeError, ValueError):
    """The bridge refused an action that can never be executed (NaN, wrong shape, degenerate rotation)."""


def spec_from_welcome(welcome: dict) -> TaskSpec:
    """Rebuild the bridge's TaskSpec from its welcome message."""
    raw = dict(welcome["spec"])
    raw["cameras"] = tuple(raw["cameras"])
    raw["lowdim"] = tuple((str(k), int(d)) for k, d in raw["lowdim"])
    names = {f.name for f in dataclasses.fields(TaskSpec)}
    return TaskSpec(**{k: v for k, v in raw.items() if k in names})


class RealRobotEnv(JEPAEnv):
    """Gymnasium client of a robot bridge (real ARX-5 or the simulated backend)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, task: str | None = None, address: str = "tcp://127.0.0.1:5555",
                 timeout_s: float = 30.0, client_name: str | None = None, manifest: dict | None = None,
                 confirmation_timeout_s: float = 900.0, render_mode: str | None = None):
        self.address = address
        self.timeout_s = float(timeout_s)
        self.confirmation_timeout_s = float(confirmation_timeout_s)
        self.manifest = dict(manifest or {})
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.DEALER)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.connect(address)
        self._seq = 0
        self._closed = False
        self._hb_thread: threading.Thread | None = None
        self._hb_stop = threading.Event()
        client = client_name or f"{socket.gethostname()}:{os.getpid()}"
        try:
            welcome = self._request({"type": P.HELLO, "task": task, "client": client}, timeout_s=self.timeout_s)
        except BaseException:
            self._close_sockets()
            raise
        self.session = welcome["session"]
        self.welcome = welcome
        spec = spec_from_welcome(welcome)
        super().__init__(spec, render_mode=render_mode)
        self.metadata = {**self.metadata, "render_fps": spec.control_hz}
        self.action_space = spaces.Box(np.asarray(welcome["action_low"], np.float32),
                                       np.asarray(welcome["action_high"], np.float32), dtype=np.float32)
        self.chunk_budget = int(welcome["chunk_budget"])
        self._last_obs: dict | None = None
        self._last_obs_time = time.monotonic()
        self._start_heartbeat(float(welcome["heartbeat_interval_s"]))

    # ------------------------------------------------------------ transport
    def _request(self, message: dict, timeout_s: float | None = None) -> dict:
        if self._closed:
            raise RuntimeError("this RealRobotEnv is closed; make a new one")
        self._seq += 1
        message = {**message, "seq": self._seq}
        if getattr(self, "session", None) is not None:
            message["session"] = self.session
        self._sock.send(P.encode(message))
        timeout = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._sock.poll(int(remaining * 1000)):
                raise TimeoutError(f"the robot bridge at {self.address} did not answer {message['type']!r} within "
                                   f"{timeout:.1f}s; check that `jepa-robot-bridge serve` runs there (and, "
                                   "at an episode's end, that the operator confirmed its outcome)")
            reply = P.decode(self._sock.recv())
            if reply.get("seq") not in (None, self._seq):
                continue   # a late answer to a request that already timed out
            if reply["type"] == P.PENDING:
                # the operator decides now; the bridge keeps watching the link meanwhile
                deadline = time.monotonic() + self.confirmation_timeout_s
                timeout = self.confirmation_timeout_s
                continue
            if reply["type"] == P.ERROR:
                code, text = reply.get("code", ""), reply.get("message", "")
                if code == P.ERR_BUSY:
                    raise BridgeBusy(code, text)
                if code == P.ERR_INVALID_ACTION:
                    raise ActionRefused(code, text)
                if code == P.ERR_VERSION:
                    raise P.ProtocolError(text)
                raise BridgeError(code, text)
            P.check_version(reply)
            return reply

    def _start_heartbeat(self, interval_s: float) -> None:
        hb = self._ctx.socket(zmq.DEALER)
        hb.setsockopt(zmq.LINGER, 0)
        hb.connect(self.address)
        beat = P.encode({"type": P.HEARTBEAT, "session": self.session})

        def run() -> None:
            try:
                while not self._hb_stop.wait(interval_s):
                    hb.send(beat, flags=zmq.NOBLOCK)
            except zmq.ZMQError:
                pass   # the context is being torn down by close()
            finally:
                hb.close(linger=0)

        self._hb_thread = threading.Thread(target=run, name="robot-heartbeat", daemon=True)
        self._hb_thread.start()

    def _close_sockets(self) -> None:
        self._hb_stop.set()
        if self._hb_thread is not None:
            self._hb_thread.join(timeout=2)
        self._sock.close(linger=0)
        self._ctx.term()

    # ------------------------------------------------------------ gym API
    def _typed_obs(self, obs: dict) -> dict:
        out = {}
        for key, space in self.observation_space.spaces.items():
            if key not in obs:
                raise P.ProtocolError(f"the bridge sent no {key!r}; bridge and client disagree on the task")
            out[key] = np.asarray(obs[key], dtype=space.dtype).reshape(space.shape)
        self._last_obs = out
        self._last_obs_time = time.monotonic()
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode on the robot (homing for hardware); ``options['manifest']`` is logged with it."""
        super().reset(seed=seed)
        manifest = {**self.manifest, **dict((options or {}).get("manifest", {}))}
        reply = self._request({"type": P.RESET, "seed": seed, "manifest": manifest})
        return self._typed_obs(reply["obs"]), reply["info"]

    def step(self, action):
        """Execute one absolute action; ``info['safety']`` reports refused or clipped actions."""
        reply = self._request({"type": P.STEP, "action": np.asarray(action, dtype=np.float64)})
        return self._result(reply)

    def step_chunk(self, actions):
        """Execute an (N, action_dim) chunk in one round trip; returns the observation after it."""
        latency = time.monotonic() - self._last_obs_time
        reply = self._request({"type": P.CHUNK, "actions": np.asarray(actions, dtype=np.float64),
                               "client_latency_s": latency})
        return self._result(reply)

    def _result(self, reply: dict):
        obs = self._typed_obs(reply["obs"])
        return obs, float(reply["reward"]), bool(reply["terminated"]), bool(reply["truncated"]), reply["info"]

    def set_render_images(self, enabled: bool) -> None:
        """Ask the bridge to skip (False) or send (True) camera images; skipped images arrive all-zero."""
        super().set_render_images(enabled)
        self._request({"type": P.RENDER_IMAGES, "enabled": bool(enabled)})

    def render(self):
        if self.render_mode != "rgb_array" or self._last_obs is None:
            return None
        return np.concatenate([self._last_obs[k] for k in self.task_spec.image_keys], axis=1)

    def close(self) -> None:
        """Give control back to the bridge (it holds the robot) and close the connection."""
        if self._closed:
            return
        try:
            self._request({"type": P.BYE}, timeout_s=2.0)
        except (TimeoutError, BridgeError):
            pass   # the bridge is gone or already dropped us; it holds the robot either way
        self._closed = True
        self._close_sockets()
        super().close()

