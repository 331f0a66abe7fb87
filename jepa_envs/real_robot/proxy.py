"""The policy side: a Gymnasium env whose robot lives behind a robot bridge.

``gym.make("JEPA/RealRobot-v0", task="Cabinet", address="tcp://robot-pc:5555")`` gives the same observation
and action conventions as the simulated envs (a Dict of ``<camera>_image`` uint8 and float32 low-dim keys,
absolute actions, ``info["is_success"]``). For the real robot ``is_success`` is the operator's confirmation
at episode end. ``step_chunk`` sends a whole action chunk in one round trip (the paper's synchronous loop,
Sec. 4.8); ``observe`` and ``stream`` drive the asynchronous loop (``executor.AsyncChunkExecutor``).

Liveness costs this process nothing: after ``hello`` the env opens a second connection, its *link*, and
``zmq.proxy`` echoes every ping the bridge sends on it from a thread that holds no GIL, so the pings are answered
also while this process is busy in a long call (inference, a C call that holds the GIL). The control
connection keeps one routing id for its lifetime, so after a network drop it reconnects as the same client and
the bridge delivers a reply it held back; a client whose session the bridge dropped gets ``LostControl`` with
the reason and can call ``reconnect()``.
"""
from __future__ import annotations

import dataclasses
import itertools
import os
import secrets
import socket
import threading
import time

import numpy as np
import zmq
from gymnasium import spaces
from zmq.utils.monitor import parse_monitor_message

from jepa_envs.tasks.base import JEPAEnv
from jepa_robot import protocol as P
from jepa_envs.tasks.spec import TaskSpec


class BridgeError(RuntimeError):
    """The bridge refused a request; ``code`` is the protocol's error code."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


class BridgeBusy(BridgeError):
    """Another client already controls the robot."""


class ActionRefused(BridgeError, ValueError):
    """The bridge refused an action that can never be executed (NaN, wrong shape, degenerate rotation)."""


class LostControl(BridgeError):
    """This client does not (or no longer) control the robot; the message says why. ``reconnect()`` retries."""


class RequestLost(BridgeError):
    """The connection dropped before the request reached the bridge: nothing of it ran; send it again."""


class HandshakeFailed(BridgeError, ConnectionRefusedError):
    """A bridge listens at the address but refused this connection's security handshake (CurveZMQ keys)."""


_HANDSHAKE_FAILURES = (zmq.EVENT_HANDSHAKE_FAILED_AUTH, zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL,
                       zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL)


def handshake_failure(event: int, address: str, with_keys: bool) -> HandshakeFailed:
    """Name why a security handshake failed, from libzmq's event and whether this client has CurveZMQ keys."""
    if event == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
        return HandshakeFailed("curve_key_refused", (
            f"the robot bridge at {address} refused this client's CurveZMQ key: its public key is not among the "
            "bridge's authorized_clients; on the robot computer run `jepa-robot-bridge keys BRIDGE_FOLDER "
            "--authorize NAME.key` with this client's public key"))
    if not with_keys:
        return HandshakeFailed("curve_required", (
            f"the robot bridge at {address} refused this connection's handshake: it requires CurveZMQ and this "
            "client has no keys; pass curve_server_key (the bridge's bridge.key) and curve_client_key (this "
            "client's .key_secret), or --curve-server-key/--curve-client-key to jepa-policy robot"))
    return HandshakeFailed("curve_handshake_failed", (
        f"the CurveZMQ handshake with the robot bridge at {address} failed: the bridge public key given "
        "(curve_server_key) is not the key of the bridge listening there (copy bridge.key from the robot "
        "computer's key folder), or that bridge does not use CurveZMQ"))


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
                 confirmation_timeout_s: float = 900.0, render_mode: str | None = None,
                 curve_server_key: str | None = None, curve_client_key: str | None = None):
        self.address = address
        self.timeout_s = float(timeout_s)
        self.confirmation_timeout_s = float(confirmation_timeout_s)
        self.manifest = dict(manifest or {})
        self._task = task
        self._client = client_name or f"{socket.gethostname()}:{os.getpid()}"
        self._ctx = zmq.Context()
        self._keys = (curve_server_key, curve_client_key)
        # one routing id for the connection's lifetime: a reconnect after a network drop is the same client
        self._routing_id = b"jepa-" + secrets.token_bytes(12)
        self._sock = self._dealer(self._routing_id)
        self._link: tuple[zmq.Socket, zmq.Socket, zmq.Socket, threading.Thread] | None = None
        self._curve = curve_server_key is not None
        # the connection's own events: a second handshake means it dropped and came back (``_request`` resumes)
        self._monitor = self._sock.get_monitor_socket(
            zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
            | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL)   # a refused handshake is named, not a silent timeout
        self._handshakes = 0
        self._poller = zmq.Poller()
        self._poller.register(self._sock, zmq.POLLIN)
        self._poller.register(self._monitor, zmq.POLLIN)
        self._sock.connect(address)
        self._seq = 0
        self._closed = False
        self.session: str | None = None
        try:
            welcome = self._hello()
        except BaseException:
            self._close_sockets()
            raise
        spec = spec_from_welcome(welcome)
        super().__init__(spec, render_mode=render_mode)
        self.metadata = {**self.metadata, "render_fps": spec.control_hz}
        self.action_space = spaces.Box(np.asarray(welcome["action_low"], np.float32),
                                       np.asarray(welcome["action_high"], np.float32), dtype=np.float32)
        self.chunk_budget = int(welcome["chunk_budget"])
        self._last_obs: dict | None = None
        self._last_obs_time = time.monotonic()

    def _dealer(self, routing_id: bytes) -> zmq.Socket:
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.ROUTING_ID, routing_id)
        sock.setsockopt(zmq.RECONNECT_IVL, 20)
        sock.setsockopt(zmq.RECONNECT_IVL_MAX, 500)
        _setup_curve_client(sock, *self._keys)
        return sock

    def _hello(self) -> dict:
        self.session = None
        welcome = self._request({"type": P.HELLO, "task": self._task, "client": self._client},
                                timeout_s=self.timeout_s)
        self.session = welcome["session"]
        self.welcome = welcome
        self._open_link()
        return welcome

    def _open_link(self) -> None:
        """The link connection: registered with the session's token, then echoed back by ``zmq.proxy``."""
        self._close_link()
        link = self._dealer(self._routing_id + b"/link-" + secrets.token_bytes(4))   # never an old link's id
        link.connect(self.address)
        link.send(P.encode({"type": P.LINK, "session": self.session}))
        steer_address = f"inproc://robot-link-{next(_LINKS)}"
        steer, steered = self._ctx.socket(zmq.PAIR), self._ctx.socket(zmq.PAIR)
        steer.bind(steer_address)
        steered.connect(steer_address)
        echo = threading.Thread(target=_echo, args=(link, steered), name="robot-link-echo", daemon=True)
        echo.start()
        self._link = (link, steer, steered, echo)

    def _close_link(self) -> None:
        if self._link is None:
            return
        link, steer, steered, echo = self._link
        steer.send(b"TERMINATE")
        echo.join(timeout=5)
        for sock in (link, steer, steered):
            sock.close(linger=0)
        self._link = None

    def reconnect(self) -> None:
        """Take control again after ``LostControl`` (the bridge refuses with ``BridgeBusy`` if another client
        took it meanwhile); call ``reset`` next: the interrupted episode is over."""
        welcome = self._hello()
        if welcome["spec"]["name"] != self.task_spec.name:
            raise P.ProtocolError(f"the bridge now serves {welcome['spec']['name']!r}, not {self.task_spec.name!r}")

    # ------------------------------------------------------------ transport
    def _request(self, message: dict, timeout_s: float | None = None) -> dict:
        if self._closed:
            raise RuntimeError("this RealRobotEnv is closed; make a new one")
        self._seq += 1
        message = {**message, "seq": self._seq}
        if getattr(self, "session", None) is not None:
            message["session"] = self.session
        self._sock.send(P.encode(message))
        answers = {self._seq}   # the request's seq and those of the resumes sent for it
        timeout = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            events = dict(self._poller.poll(int(remaining * 1000))) if remaining > 0 else {}
            if not events:
                raise TimeoutError(f"the robot bridge at {self.address} did not answer {message['type']!r} within "
                                   f"{timeout:.1f}s; check that `jepa-robot-bridge serve` runs there (and, "
                                   "at an episode's end, that the operator confirmed its outcome)")
            if self._monitor in events:
                if self._reconnected() and self.session is not None and message["type"] != P.HELLO:
                    # the connection dropped and came back: ask again for the reply this request waits for
                    self._seq += 1
                    answers.add(self._seq)
                    self._sock.send(P.encode({"type": P.RESUME, "seq": self._seq, "session": self.session,
                                              "awaiting": message["seq"]}))
                continue
            if self._sock not in events:
                continue
            reply = P.decode(self._sock.recv())
            if reply["type"] == P.LINK or reply.get("seq") not in answers | {None}:
                continue   # a link notice, or a late answer to a request that already timed out
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
                if code == P.ERR_NOT_CONTROLLING:
                    raise LostControl(code, text)
                if code == P.ERR_LOST:
                    raise RequestLost(code, text)
                raise BridgeError(code, text)
            P.check_version(reply)
            return reply

    def _reconnected(self) -> bool:
        """Read one connection event; True when it is a handshake after the first (a reconnection).

        A refused security handshake raises HandshakeFailed at once: libzmq would retry it forever with the same
        keys, and the caller would otherwise only see a timeout that looks like no bridge at all."""
        event = parse_monitor_message(self._monitor.recv_multipart())
        if event["event"] in _HANDSHAKE_FAILURES:
            raise handshake_failure(event["event"], self.address, self._curve)
        if event["event"] != zmq.EVENT_HANDSHAKE_SUCCEEDED:
            return False
        self._handshakes += 1
        return self._handshakes > 1

    def _close_sockets(self) -> None:
        self._close_link()
        try:
            self._sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._monitor.close(linger=0)
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

    def observe(self, history: int = 1) -> tuple[list[dict], dict]:
        """The newest ``history`` observations, oldest first, and the bridge's info (``step``: the newest one's
        episode step, ``queue``, ``underflow_steps``, ``outcome`` ...). Moves nothing."""
        reply = self._request({"type": P.OBSERVE, "history": int(history)})
        return [self._typed_obs(o) for o in reply["obs_history"]], reply["info"]

    def stream(self, actions, origin_step: int) -> dict:
        """Asynchronous execution: replace the bridge's queue with this chunk, predicted from the observation of
        episode step ``origin_step``. The bridge drops the actions whose time has passed (``late_steps``) and
        runs the rest at the control rate; returns ``accepted``, ``late_steps``, ``step``, ``underflow_steps``."""
        return self._request({"type": P.STREAM, "actions": np.asarray(actions, dtype=np.float64),
                              "origin_step": int(origin_step)})

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
            if self.session is not None:
                self._request({"type": P.BYE}, timeout_s=2.0)
        except (TimeoutError, BridgeError):
            pass   # the bridge is gone or already dropped us; it holds the robot either way
        self._closed = True
        self._close_sockets()
        super().close()



_LINKS = itertools.count()


def _echo(link: zmq.Socket, steered: zmq.Socket) -> None:
    """Send every message the bridge sends on the link straight back, inside libzmq (no GIL), until TERMINATE."""
    try:
        zmq.proxy_steerable(link, link, None, steered)
    except zmq.ContextTerminated:
        pass


def _setup_curve_client(sock: zmq.Socket, server_key: str | None, client_key: str | None) -> None:
    """CurveZMQ: encrypt and authenticate the connection (keys from ``jepa-robot-bridge keys``)."""
    if server_key is None and client_key is None:
        return
    if server_key is None or client_key is None:
        raise ValueError("CurveZMQ needs both curve_server_key (the bridge's public key file) and "
                         "curve_client_key (this client's secret key file)")
    import zmq.auth

    server_public, _ = zmq.auth.load_certificate(server_key)
    public, secret = zmq.auth.load_certificate(client_key)
    if secret is None:
        raise ValueError(f"{client_key} holds no secret key; pass the client's '.key_secret' file")
    sock.curve_serverkey, sock.curve_publickey, sock.curve_secretkey = server_public, public, secret
