"""``jepa-policy serve``: JEPA Policy behind openpi's websocket protocol, with the future-consistency monitor inside.

The wire is openpi's own (Physical-Intelligence/openpi: ``packages/openpi-client`` and
``src/openpi/serving/websocket_policy_server.py``), so a robot loop written for openpi's ``WebsocketClientPolicy``
drives this server unchanged:

* one websocket per robot; ``GET /healthz`` answers ``OK``; a non-loopback server needs the header
  ``Authorization: Api-Key <key>`` (openpi-client's ``api_key``) or TLS;
* on connect the server sends its metadata; then each binary frame from the client is one request, a map packed
  with msgpack in which numpy arrays are ``{b"__ndarray__": True, b"data", b"dtype", b"shape"}`` (openpi's
  ``msgpack_numpy``; object, void and complex arrays are refused, nothing is ever pickled), answered by one map:
  ``actions`` (the chunk to execute, unnormalised, in the task's action space), ``server_timing`` (``infer_ms``,
  ``queue_ms``, ``prev_total_ms``), ``step``, ``episode`` and, with the monitor on, ``monitor``;
* a request that cannot be used is answered with a text frame naming the problem (openpi's client raises it as a
  RuntimeError) and, unlike openpi's server, the connection stays open for the next request.

Requests: the task's observation keys (``metadata["observation"]``), each either the newest frame (the server
keeps the history the policy needs, ``obs_steps`` frames) or the newest ``n <= obs_steps`` frames stacked on a
leading axis (a loop that calls once per chunk sends its own history). Optional fields: ``episode`` (an id; a new
one starts an episode), ``reset`` (start a new episode), ``step`` (the newest frame's episode step; default: the
step after the previous request's), ``outcome`` (true/false: the episode succeeded or failed; ends it),
``observe`` (feed frames only: no actions, e.g. the frames between two chunks the monitor scores), ``full_chunk``
(all H predicted actions instead of the ``n_action_steps`` executed ones).

Monitor (``--monitor-url``): each decision's z_hat for step t + k and the realized latent E_rgb(o_{t+k}) (when a
request carries that frame) go to the monitor service through its ``MonitorClient``: a bounded buffer and a
background sender, so a reply never waits for the monitor (a down monitor costs a buffer append, microseconds; the
buffer holds 100,000 records, about 1.4 hours of one robot scoring every step at 10 Hz, before it drops and
counts). Each reply carries the NMSE of the decision whose target frame it brought, and the latest alert state the
monitor returned for the episode.

Clients are served concurrently; requests that wait together are batched into one forward pass (up to
``--max-batch``); beyond ``--max-queue`` waiting requests a request is refused with a message to retry.
"""
from __future__ import annotations

import asyncio
import hmac
import http
import logging
import socket
import ssl
import threading
import time
import uuid
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np
import torch
import websockets
from websockets.asyncio.server import ServerConnection, serve
from websockets.http11 import Request, Response

from jepa_envs.real_robot.protocol import is_loopback_host
from jepa_policy.evaluate import nmse
from jepa_policy.policy import Policy, predict_frames
from monitor_service.client import MonitorClient

log = logging.getLogger(__name__)

MAX_REQUEST_BYTES = 8 * 2**20      # a larger request is answered with an error; the connection stays open
HARD_FRAME_BYTES = 64 * 2**20      # a frame above this closes the connection (websockets' own limit, code 1009)
MONITOR_BUFFER = 100_000


class RequestError(ValueError):
    """A request the server cannot use; its message goes back to the client as a text frame."""


# ----------------------------------------------------------------------------- openpi's msgpack-numpy wire


def _pack_default(obj):
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind in ("V", "O", "c"):
        raise TypeError(f"unsupported dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot pack {type(obj).__name__}")


def pack(obj) -> bytes:
    """openpi's ``msgpack_numpy.packb``: arrays as maps with bytes keys, raw little-endian data."""
    return msgpack.packb(obj, default=_pack_default, use_bin_type=True)


def _unpack_hook(obj: dict):
    if b"__ndarray__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in ("V", "O", "c"):
            raise RequestError(f"arrays of dtype {dtype} are refused; send numeric arrays")
        shape = tuple(int(s) for s in obj[b"shape"])
        data = obj[b"data"]
        if any(s < 0 for s in shape) or len(data) != int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
            raise RequestError(f"an array's data has {len(data)} bytes, its shape {list(shape)} of {dtype} needs "
                               f"{int(np.prod(shape, dtype=np.int64)) * dtype.itemsize}")
        return np.frombuffer(data, dtype=dtype).reshape(shape).copy()
    if b"__npgeneric__" in obj:
        return np.dtype(obj[b"dtype"]).type(obj[b"data"])
    return obj


def unpack(data: bytes):
    """openpi's ``msgpack_numpy.unpackb``, checked: any decoding problem is a RequestError naming it."""
    try:
        return msgpack.unpackb(data, object_hook=_unpack_hook, strict_map_key=False)
    except RequestError:
        raise
    except Exception as exc:   # msgpack and numpy raise many types for hostile bytes
        raise RequestError(f"the request is not msgpack as openpi-client packs it ({type(exc).__name__}: "
                           f"{str(exc)[:120]})") from None


# ----------------------------------------------------------------------------- requests


@dataclass
class Parsed:
    frames: list[dict]            # newest last, unbatched arrays
    episode: str | None
    reset: bool
    step: int | None
    outcome: bool | None
    observe: bool
    full_chunk: bool


def parse_request(msg, policy: Policy) -> Parsed:
    """Check a decoded request against the task: keys, shapes, dtypes, finite values, control fields."""
    spec = policy.spec
    if not isinstance(msg, dict):
        raise RequestError(f"a request is a map of observation keys, got {type(msg).__name__}")
    msg = {k.decode() if isinstance(k, bytes) else k: v for k, v in msg.items()}
    shapes = observation_shapes(policy)
    control = {}
    for name, kind in (("episode", (str, int)), ("reset", bool), ("step", int), ("outcome", bool),
                       ("observe", bool), ("full_chunk", bool)):
        value = msg.get(name)
        if isinstance(value, np.generic):
            value = value.item()
        if value is not None and (not isinstance(value, kind) or (kind is int and isinstance(value, bool))):
            raise RequestError(f"'{name}' must be {kind.__name__ if isinstance(kind, type) else 'str or int'}, "
                               f"got {type(value).__name__}")
        control[name] = value
    if control["step"] is not None and not 0 <= control["step"] < 2**31:
        raise RequestError(f"'step' must be an episode step >= 0, got {control['step']}")
    only_control = control["outcome"] is not None or control["reset"]
    present = [k for k in shapes if k in msg]
    if not present and only_control:
        frames: list[dict] = []
    else:
        missing = [k for k in shapes if k not in msg]
        if missing:
            raise RequestError(f"the observation lacks {missing}; task {spec.name} needs "
                               + ", ".join(f"{k} {dt}{list(sh)}" for k, (sh, dt) in shapes.items())
                               + " (see the metadata's 'observation')")
        arrays = {}
        count = None
        for key, (shape, dtype) in shapes.items():
            arr = np.asarray(msg[key])
            if arr.shape == shape:
                arr = arr[None]
            elif not (arr.ndim == len(shape) + 1 and arr.shape[1:] == shape and 1 <= arr.shape[0] <= policy.obs_steps):
                raise RequestError(f"{key} has shape {list(arr.shape)}; send {list(shape)} (the newest frame) or "
                                   f"[n, {', '.join(map(str, shape))}] with n <= {policy.obs_steps} (the newest frames)")
            if arr.dtype != np.dtype(dtype):
                if dtype == "uint8" or arr.dtype.kind not in "fiu":
                    raise RequestError(f"{key} has dtype {arr.dtype}; send {dtype}")
                arr = arr.astype(dtype)
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                raise RequestError(f"{key} has NaN or infinite values; send finite values")
            if count is not None and arr.shape[0] != count:
                raise RequestError(f"{key} stacks {arr.shape[0]} frames, another key {count}; send the same number")
            count = arr.shape[0]
            arrays[key] = arr
        frames = [{k: v[i] for k, v in arrays.items()} for i in range(count)]
    episode = control["episode"]
    return Parsed(frames, None if episode is None else str(episode)[:128], bool(control["reset"]), control["step"],
                  control["outcome"], bool(control["observe"]), bool(control["full_chunk"]))


def observation_shapes(policy: Policy) -> dict[str, tuple[tuple[int, ...], str]]:
    spec = policy.spec
    shapes = {k: ((spec.image_size, spec.image_size, 3), "uint8") for k in spec.image_keys}
    shapes.update({k: ((d,), "float32") for k, d in spec.lowdim})
    return shapes


# ----------------------------------------------------------------------------- sessions (one robot each)


@dataclass
class Session:
    """One connection's episode: its frame history, step counter and the predictions awaiting their target."""

    id: str
    policy: Policy
    episode: str = ""
    episodes: int = 0
    history: deque = field(default_factory=deque)
    step: int = -1                                   # episode step of the newest frame seen
    pending: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)   # target step -> (t, z_hat)
    prev_total_ms: float | None = None

    def new_episode(self, episode: str | None) -> None:
        self.episodes += 1
        self.episode = episode or f"{self.id}-{self.episodes}"
        self.history = deque(maxlen=self.policy.obs_steps)
        self.step = -1
        self.pending = {}

    def feed(self, frames: list[dict], newest_step: int | None) -> tuple[list[tuple[int, dict]], bool]:
        """Add frames (newest last) to the history; returns their (step, frame) and whether the history had to
        be padded (a gap in the steps: as at an episode's start, the oldest frame repeats)."""
        newest = self.step + len(frames) if newest_step is None else newest_step
        steps = list(range(newest - len(frames) + 1, newest + 1))
        padded = bool(self.history) and steps[0] != self.step + 1
        if padded or len(frames) >= self.policy.obs_steps:
            self.history.clear()
        for frame in frames:
            if not self.history:
                self.history.extend([frame] * (self.policy.obs_steps - 1))
            self.history.append(frame)
        self.step = newest
        return list(zip(steps, frames)), padded


# ----------------------------------------------------------------------------- batching


@dataclass
class Work:
    """What one request needs from the model: a decision from a history, and the latents of target frames."""

    history: list[dict] | None
    targets: list[dict]
    future: asyncio.Future
    queued_at: float = field(default_factory=time.perf_counter)


class Batcher:
    """Requests that wait together share one forward pass, on one worker thread (the event loop keeps reading)."""

    def __init__(self, policy: Policy, max_batch: int, max_queue: int):
        self.policy, self.max_batch, self.max_queue = policy, max_batch, max_queue
        self.queue: asyncio.Queue[Work] = asyncio.Queue()
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jepa-serve-model")
        self.batches = self.items = 0
        self.task: asyncio.Task | None = None

    def start(self) -> None:
        self.task = asyncio.get_running_loop().create_task(self._run())

    async def submit(self, work: Work) -> tuple[np.ndarray | None, np.ndarray | None, list[np.ndarray], dict]:
        if self.queue.qsize() >= self.max_queue:
            raise RequestError(f"the server is busy: {self.queue.qsize()} requests are waiting (limit "
                               f"{self.max_queue}); retry shortly, or start another server")
        self.queue.put_nowait(work)
        return await work.future

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            batch = [await self.queue.get()]
            while len(batch) < self.max_batch and not self.queue.empty():
                batch.append(self.queue.get_nowait())
            start = time.perf_counter()
            try:
                results = await loop.run_in_executor(self.executor, self._forward, batch)
            except Exception as exc:   # a model failure answers every waiting request, the server goes on
                log.exception("inference failed")
                for work in batch:
                    if not work.future.done():
                        work.future.set_exception(RequestError(f"inference failed ({type(exc).__name__}: {exc})"))
                continue
            infer_ms = (time.perf_counter() - start) * 1e3
            self.batches += 1
            self.items += len(batch)
            for work, (actions, z_hat, latents) in zip(batch, results):
                if not work.future.done():   # the client may have gone meanwhile
                    work.future.set_result((actions, z_hat, latents, {
                        "infer_ms": infer_ms, "queue_ms": (start - work.queued_at) * 1e3, "batch": len(batch)}))

    def _forward(self, batch: list[Work]) -> list[tuple]:
        policy = self.policy
        deciding = [w for w in batch if w.history is not None]
        actions = z_hat = None
        if deciding:
            frames = [{k: np.stack([w.history[i][k] for w in deciding]) for k in deciding[0].history[i]}
                      for i in range(policy.obs_steps)]
            actions, z_hat = predict_frames(policy.model, policy.spec, frames, policy.device,
                                            want_future=policy.model.cfg.has_future_token)
        targets = [f for w in batch for f in w.targets]
        latents = list(policy.encode_future({k: np.stack([f[k] for f in targets]) for k in policy.spec.image_keys})) \
            if targets else []
        out, d, latent_iter = [], 0, iter(latents)
        for w in batch:
            mine = [next(latent_iter) for _ in w.targets]
            if w.history is not None:
                out.append((actions[d], None if z_hat is None else z_hat[d], mine))
                d += 1
            else:
                out.append((None, None, mine))
        return out


# ----------------------------------------------------------------------------- the server


@dataclass
class ServeConfig:
    host: str = "127.0.0.1"
    port: int = 8000
    api_key: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    max_batch: int = 16
    max_queue: int = 64
    monitor_url: str | None = None
    monitor_key: str | None = None
    task_id: str | None = None          # the monitor's task name (default: the checkpoint's task)
    robot: str | None = None            # the monitor key's robot
    monitor_buffer: int = MONITOR_BUFFER


def check_config(config: ServeConfig) -> None:
    """Refuse a configuration that cannot serve safely, before any checkpoint is loaded."""
    if not is_loopback_host(config.host) and not (config.api_key or config.tls_cert):
        raise ValueError(f"--host {config.host} is reachable from the network: pass --api-key KEY (clients send "
                         "'Authorization: Api-Key KEY', openpi-client's api_key) or --tls-cert/--tls-key; a "
                         "policy server drives robots")
    if (config.tls_cert is None) != (config.tls_key is None):
        raise ValueError("TLS needs both --tls-cert and --tls-key")
    if config.monitor_url and not config.monitor_key:
        raise ValueError("--monitor-url needs --monitor-key (a robot key of the monitor service)")
    if config.max_batch < 1 or config.max_queue < 1:
        raise ValueError("--max-batch and --max-queue must be >= 1")


class PolicyServer:
    """Serves one checkpoint's policy to any number of robots over openpi's websocket protocol."""

    def __init__(self, policy: Policy, config: ServeConfig, checkpoint: str = ""):
        check_config(config)
        self.policy, self.config, self.checkpoint = policy, config, checkpoint
        self.metadata = server_metadata(policy, checkpoint, config)
        self.monitor: MonitorClient | None = None
        self.alerts: dict[str, int | None] = {}
        self._alerts_lock = threading.Lock()
        self.batcher: Batcher | None = None
        self.connections = 0
        self.port: int | None = None
        self.ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------ monitor
    def _on_monitor_result(self, records: list[dict], result: dict) -> None:
        with self._alerts_lock:
            self.alerts.update(result.get("alert_state") or {})

    def _monitor_state(self, session: Session, scored: list[dict]) -> dict:
        with self._alerts_lock:
            alert_id = self.alerts.get(session.episode)
        state = {"episode": session.episode, "alert": alert_id is not None, "alert_id": alert_id,
                 "scored": scored, "nmse": scored[-1]["nmse"] if scored else None}
        if self.monitor is not None:
            state.update(pending_records=self.monitor.pending, dropped_records=self.monitor.stats.dropped)
        return state

    # ------------------------------------------------------------ websocket
    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        if request.path == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        if self.config.api_key is not None:
            given = request.headers.get("Authorization", "")
            expected = f"Api-Key {self.config.api_key}"
            if not hmac.compare_digest(given.encode(), expected.encode()):
                return connection.respond(http.HTTPStatus.UNAUTHORIZED,
                                          "missing or wrong 'Authorization: Api-Key <key>' header\n")
        return None

    async def _handler(self, ws: ServerConnection) -> None:
        self.connections += 1
        session = Session(uuid.uuid4().hex[:8], self.policy)
        session.new_episode(None)
        try:
            await ws.send(pack(self.metadata))
            async for message in ws:
                start = time.monotonic()
                try:
                    reply = await self._answer(session, message)
                except RequestError as exc:
                    await ws.send(f"jepa-policy serve: {exc}")
                    continue
                reply["server_timing"]["prev_total_ms"] = session.prev_total_ms
                await ws.send(pack(reply))
                session.prev_total_ms = (time.monotonic() - start) * 1e3
        except websockets.ConnectionClosed:
            pass   # a client that leaves mid-request: its result is dropped, nothing else changes
        finally:
            self.connections -= 1

    async def _answer(self, session: Session, message) -> dict:
        if isinstance(message, str):
            raise RequestError("send binary frames packed with msgpack (openpi-client's packer), not text")
        if len(message) > MAX_REQUEST_BYTES:
            raise RequestError(f"the request has {len(message)} bytes, above the limit {MAX_REQUEST_BYTES}; send "
                               "the task's observation keys only, at the metadata's shapes")
        parsed = parse_request(unpack(message), self.policy)
        if parsed.reset or (parsed.episode is not None and parsed.episode != session.episode):
            session.new_episode(parsed.episode)
        fed, padded = session.feed(parsed.frames, parsed.step) if parsed.frames else ([], False)
        # realized latents only for the monitor: without it a reply costs one decision, as in-process act
        targets = [(s, f) for s, f in fed if s in session.pending] if self.monitor is not None else []
        want_actions = bool(parsed.frames) and not parsed.observe and parsed.outcome is None
        reply: dict = {"episode": session.episode, "step": session.step, "server_timing": {}}
        if want_actions or targets:
            actions, z_hat, latents, timing = await self.batcher.submit(Work(
                list(session.history) if want_actions else None, [f for _, f in targets],
                asyncio.get_running_loop().create_future()))
            reply["server_timing"].update(timing)
        else:
            actions, z_hat, latents = None, None, []
        scored = []
        for (s, _), z_real in zip(targets, latents):
            t, predicted = session.pending.pop(s)
            value = float(nmse(predicted, z_real))
            scored.append({"decision_step": t, "target_step": s, "nmse": value})
            if self.monitor is not None:
                self.monitor.target(session.episode, s, z_real)
        if actions is not None:
            chunk = actions if parsed.full_chunk else actions[: self.policy.n_action_steps]
            reply["actions"] = np.ascontiguousarray(chunk, dtype=np.float32)
            if z_hat is not None and self.monitor is not None:
                session.pending[session.step + self.policy.k] = (session.step, z_hat)
                self.monitor.decision(self.config.task_id or self.policy.spec.name, session.episode, session.step,
                                      self.policy.k, z_hat, checkpoint=self.checkpoint or None)
        if padded:
            reply["history_padded"] = True
        if parsed.outcome is not None:
            if self.monitor is not None:
                self.monitor.outcome(session.episode, parsed.outcome, length=session.step + 1)
            reply["ended"] = {"episode": session.episode, "success": parsed.outcome}
            session.new_episode(None)
        if self.monitor is not None or scored:
            reply["monitor"] = self._monitor_state(session, scored)
        return reply

    # ------------------------------------------------------------ lifecycle
    async def serve(self) -> None:
        ctx = None
        if self.config.tls_cert:
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ctx.load_cert_chain(self.config.tls_cert, self.config.tls_key)
        if self.config.monitor_url:
            self.monitor = MonitorClient(self.config.monitor_url, self.config.monitor_key, robot=self.config.robot,
                                         max_buffer=self.config.monitor_buffer, on_result=self._on_monitor_result)
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self.batcher = Batcher(self.policy, self.config.max_batch, self.config.max_queue)
        self.batcher.start()
        try:
            async with serve(self._handler, self.config.host, self.config.port, ssl=ctx, compression=None,
                             max_size=HARD_FRAME_BYTES, process_request=self._process_request) as server:
                self.port = next(s.getsockname()[1] for s in server.sockets if s.family in (socket.AF_INET,
                                                                                              socket.AF_INET6))
                self.ready.set()
                await self._stop.wait()
        finally:
            self.batcher.task.cancel()
            self.batcher.executor.shutdown(wait=False)
            if self.monitor is not None:
                self.monitor.close(timeout=10)

    def run(self) -> None:
        asyncio.run(self.serve())

    def start_in_thread(self) -> "PolicyServer":
        """Serve from a background thread (tests, benchmarks); returns once the port is bound."""
        self._thread = threading.Thread(target=self.run, name="jepa-policy-serve", daemon=True)
        self._thread.start()
        if not self.ready.wait(60):
            raise RuntimeError("the policy server did not start")
        return self

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if getattr(self, "_thread", None) is not None:
            self._thread.join(timeout=30)


def server_metadata(policy: Policy, checkpoint: str, config: ServeConfig) -> dict:
    """What a client learns on connect: the task, every observation key with its shape and dtype, the chunk."""
    spec = policy.spec
    return {
        "server": "jepa-policy", "protocol": "openpi websocket (msgpack-numpy)", "task": spec.name,
        "env_id": spec.env_id, "checkpoint": Path(checkpoint).name if checkpoint else None,
        "checkpoint_step": policy.checkpoint_step, "arm": policy.model.cfg.arm,
        "observation": {k: {"shape": list(sh), "dtype": dt} for k, (sh, dt) in observation_shapes(policy).items()},
        "obs_steps": policy.obs_steps,
        "action": {"dim": spec.action_dim, "chunk": [policy.n_action_steps, spec.action_dim], "horizon": spec.horizon,
                   "convention": "absolute" if spec.suite != "embedded" else "absolute agent target (pixels)"},
        "control_hz": spec.control_hz, "future_k": policy.k,
        "request_fields": {"episode": "str or int: a new id starts an episode", "reset": "bool: new episode",
                           "step": "int: the newest frame's episode step", "outcome": "bool: the episode's result",
                           "observe": "bool: feed frames only", "full_chunk": "bool: all H actions"},
        "monitor": None if not config.monitor_url else {"task_id": config.task_id or spec.name},
        "limits": {"max_request_bytes": MAX_REQUEST_BYTES, "max_batch": config.max_batch,
                   "max_queue": config.max_queue},
    }


def serve_checkpoint(checkpoint: str, config: ServeConfig, device: str = "cpu", threads: int | None = None) -> None:
    """Load a checkpoint (refused unread if it is not plain data) and serve it until interrupted."""
    check_config(config)
    if threads:
        torch.set_num_threads(threads)
    policy = Policy.from_checkpoint(checkpoint, device=device)
    server = PolicyServer(policy, config, checkpoint)
    print(f"jepa-policy serve: {policy.spec.name} ({policy.model.cfg.arm}, step {policy.checkpoint_step}) on "
          f"{'wss' if config.tls_cert else 'ws'}://{config.host}:{config.port}"
          + (f", monitor {config.monitor_url}" if config.monitor_url else ""), flush=True)
    try:
        server.run()
    except KeyboardInterrupt:
        pass
