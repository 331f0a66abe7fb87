"""The policy server: websocket connections (auth, the connection cap, TLS), one session per robot, requests
decoded off the event loop, decisions through the batcher, the monitor inside, and the event log.

Memory is bounded before anything is read: websockets refuses a frame above ``MAX_REQUEST_BYTES`` from its header
(close code 1009), reads a connection's next frame only once the previous one is taken (``max_queue=0``), and a
connection beyond ``--max-connections`` is refused at the handshake (HTTP 503), so buffered requests stay under
about 2 x ``max_connections`` x ``MAX_REQUEST_BYTES``.

Refused requests are paced per peer address (the host: a client that reconnects after every refused frame keeps
its record): each one adds 1 to the address's penalty (which halves every ``PENALTY_HALF_LIFE_S`` seconds); from
the second one on, the connection's next frame is read only after a pause that doubles with the penalty
(``PACE_FIRST_S`` up to ``PACE_MAX_S``), a new connection from that address waits the same pause before its
first frame is read, and the eighth refused in a row closes the connection (1008) after the longest pause; from
then on, until the penalty has decayed, that address's handshakes are answered 429 after ``PACE_MAX_S``. A
robot whose one frame is wrong hears of it at once; a client that sends junk in a loop, reconnecting or not, gets
about 8 frames in 5 s instead of as many as the server can decode. Requests the server itself fails on (a bug, a
MemoryError) are paced the same way, answered in one line and logged as one JSON line with the traceback as a
field.

The monitor's state is bounded: a session keeps at most ``MAX_PENDING`` predictions waiting for their target
frame (one whose target step passed unseen is dropped), and the alert state of an episode is kept only while a
session runs it.
"""
from __future__ import annotations

import asyncio
import hmac
import http
import math
import socket
import ssl
import sys
import threading
import time
import traceback
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
import websockets
from websockets.asyncio.server import ServerConnection, serve
from websockets.http11 import Request, Response

from jepa_policy.detectors import stac
from jepa_policy.policy import Policy
from jepa_policy.serve.batcher import Batcher, ServerBusy, Work
from jepa_policy.serve.codec import MAX_ARRAYS, MAX_MAPS, MAX_REQUEST_BYTES, RequestError, pack
from jepa_policy.serve.config import ServeConfig, check_config
from jepa_policy.serve.events import EventLog, log_to_stderr
from jepa_policy.serve.request import RequestSchema, decode_request
from jepa_policy.serve.sessions import PeerPenalties, Session
from monitor_service.client import MonitorClient
from monitor_service.scoring import nmse


PENALTY_HALF_LIFE_S = 60.0
PENALTY_CLOSE = 7.5         # refused requests (decayed) at which a connection is closed: the 8th in a row
PACE_FIRST_S = 0.05         # the pause after the second refused request; it doubles with each next one
PACE_MAX_S = 2.0
MAX_PENDING = 64            # predictions a session keeps waiting for their target frame


class _Connection(ServerConnection):
    """Once websockets closes a connection for a frame above ``max_size`` (1009), the rest of that frame is not
    read: reading pauses (the client's sends stall on a full TCP window) and the socket is dropped after
    ``OVERSIZE_DROP_S``; websockets would otherwise read and discard up to the whole frame on the event loop."""

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        sent = self.protocol.close_sent
        if sent is not None and sent.code == 1009 and not getattr(self, "_dropping", False):
            self._dropping = True
            self.transport.pause_reading()
            self.loop.call_later(OVERSIZE_DROP_S, self.transport.abort)


OVERSIZE_DROP_S = 1.0


def _peer(connection: ServerConnection) -> str:
    address = connection.remote_address
    return f"{address[0]}:{address[1]}" if address else "?"


def _host(connection: ServerConnection) -> str:
    address = connection.remote_address
    return str(address[0]) if address else "?"


def _pause(penalty: float) -> float:
    """The pause after refused requests worth ``penalty`` (decayed): none for one, then doubling from the second."""
    return min(PACE_MAX_S, PACE_FIRST_S * 2 ** max(0, round(penalty) - 2)) if penalty >= 1.5 else 0.0


class _HandshakeWatch(ssl.SSLObject):
    """The TLS side of a connection (``SSLContext.sslobject_class``): a refused handshake (an unknown client
    certificate, none, plain HTTP on the TLS port) calls ``on_refused`` with the reason and the peer; asyncio
    itself says nothing of it outside its debug mode."""

    on_refused = None   # set per context (``PolicyServer._tls_context``)

    def do_handshake(self):
        try:
            return super().do_handshake()
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise
        except (ssl.SSLError, OSError) as exc:
            if self.on_refused is not None:
                self.on_refused(exc, _handshake_peer())
            raise


def _handshake_peer() -> str:
    """The address of the connection whose handshake asyncio's SSL protocol is running (its caller's frame)."""
    import asyncio.sslproto
    frame = sys._getframe(2)
    while frame is not None:
        owner = frame.f_locals.get("self")
        if isinstance(owner, asyncio.sslproto.SSLProtocol):
            try:
                address = owner._transport.get_extra_info("peername")
                return f"{address[0]}:{address[1]}"
            except Exception:   # the transport is gone: the line still names the refusal
                return "?"
        frame = frame.f_back
    return "?"


class PolicyServer:
    """Serves one checkpoint's policy to any number of robots over openpi's websocket protocol."""

    def __init__(self, policy: Policy, config: ServeConfig, checkpoint: str = "", events: EventLog | None = None):
        check_config(config)
        self.policy, self.config, self.checkpoint = policy, config, checkpoint
        self.schema = RequestSchema.of(policy)
        self.metadata = server_metadata(policy, checkpoint, config)
        self.events = events or EventLog()
        self.monitor: MonitorClient | None = None
        self.alerts: dict[str, int | None] = {}        # the alert state of episodes a session runs now
        self._live: dict[str, int] = {}                   # episode id -> sessions running it
        self._alerts_lock = threading.Lock()
        self.penalties = PeerPenalties(PENALTY_HALF_LIFE_S)
        self.batcher: Batcher | None = None
        self.decoder = ThreadPoolExecutor(max_workers=2, thread_name_prefix="jepa-serve-decode")
        self.connections = 0
        self._admitted: set[ServerConnection] = set()
        self.port: int | None = None
        self.ready = threading.Event()
        self.on_ready = None   # called with the bound port once the server listens (the CLI's banner)
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------ monitor
    def _on_monitor_result(self, records: list[dict], result: dict) -> None:
        with self._alerts_lock:   # an answer may come after its episode ended: only live episodes are kept
            self.alerts.update({e: a for e, a in (result.get("alert_state") or {}).items() if e in self._live})

    def _new_episode(self, session: Session, episode: str | None) -> None:
        """Start the session's next episode; the one it ends leaves the alert map (unless another session runs
        an episode of the same id)."""
        self._end_episode(session)
        session.new_episode(episode)
        with self._alerts_lock:
            self._live[session.episode] = self._live.get(session.episode, 0) + 1

    def _end_episode(self, session: Session) -> None:
        with self._alerts_lock:
            if session.episode in self._live:
                self._live[session.episode] -= 1
                if not self._live[session.episode]:
                    del self._live[session.episode]
                    self.alerts.pop(session.episode, None)

    def _monitor_state(self, session: Session, scored: list[dict]) -> dict:
        with self._alerts_lock:
            alert_id = self.alerts.get(session.episode)
        state = {"episode": session.episode, "alert": alert_id is not None, "alert_id": alert_id,
                 "scored": scored, "nmse": scored[-1]["nmse"] if scored else None}
        if self.monitor is not None:
            state.update(pending_records=self.monitor.pending, dropped_records=self.monitor.stats.dropped)
        return state

    # ------------------------------------------------------------ websocket
    async def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        if request.path == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        peer = _peer(connection)
        penalty = self.penalties.current(_host(connection), time.monotonic())
        if penalty >= PENALTY_CLOSE:   # an address whose requests keep being refused: slowed, then turned away
            await asyncio.sleep(PACE_MAX_S)
            self.events.emit("refused", peer=peer, status=429, penalty=round(penalty, 2))
            return connection.respond(http.HTTPStatus.TOO_MANY_REQUESTS,
                                      f"{penalty:.0f} recent requests from {_host(connection)} were refused; fix the "
                                      "client (see the text replies) and retry in a minute\n")
        if self.config.api_key is not None:
            given = request.headers.get_all("Authorization")
            expected = f"Api-Key {self.config.api_key}".encode()
            if len(given) != 1 or not hmac.compare_digest(given[0].encode(), expected):
                problem = ("no Authorization header" if not given else f"{len(given)} Authorization headers"
                           if len(given) > 1 else "a wrong key")
                self.events.emit("unauthorized", peer=peer, status=401, problem=problem)
                return connection.respond(http.HTTPStatus.UNAUTHORIZED, "send one 'Authorization: Api-Key <key>' "
                                          "header with the server's key (openpi-client's api_key)\n")
        self._admitted = {c for c in self._admitted if not c.transport.is_closing()}
        if len(self._admitted) >= self.config.max_connections:
            self.events.emit("refused", peer=peer, status=503, connections=len(self._admitted),
                             limit=self.config.max_connections)
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                      f"the server has {len(self._admitted)} connections, its limit "
                                      "(--max-connections); retry later, or raise the limit\n")
        self._admitted.add(connection)
        return None

    async def _handler(self, ws: ServerConnection) -> None:
        self.connections += 1
        session = Session(uuid.uuid4().hex[:8], self.policy.obs_steps, peer=_peer(ws))
        self._new_episode(session, None)
        opened = time.monotonic()
        self.events.emit("connect", peer=session.peer, session=session.id,
                         client=", ".join(ws.request.headers.get_all("User-Agent"))[:200] or None)
        try:
            await ws.send(pack(self.metadata))
            # a new connection from an address with refused requests waits their pause before its first frame
            await asyncio.sleep(_pause(self.penalties.current(_host(ws), time.monotonic())))
            async for message in ws:
                start = time.monotonic()
                session.requests += 1
                try:
                    reply = await self._answer(session, message)
                except ServerBusy as exc:
                    self.events.emit("busy", peer=session.peer, session=session.id, queue=self.batcher.queue.qsize())
                    await ws.send(f"jepa-policy serve: {exc}")
                    continue
                except RequestError as exc:
                    self.events.emit("rejected", peer=session.peer, session=session.id, problem=str(exc)[:300])
                    await ws.send(f"jepa-policy serve: {exc}")
                    await self._pace(ws, session)
                    continue
                except Exception as exc:   # a bug of ours (or MemoryError): one line back, one JSON line logged
                    self.events.emit("error", peer=session.peer, session=session.id,
                                     problem=f"{type(exc).__name__}: {exc}"[:300],
                                     traceback="".join(traceback.format_exception(exc))[-4000:])
                    await ws.send(f"jepa-policy serve: the server failed on this request ({type(exc).__name__}); "
                                  "a bug of the server: report it with the server's log")
                    await self._pace(ws, session)
                    continue
                reply["server_timing"]["prev_total_ms"] = session.prev_total_ms
                await ws.send(pack(reply))
                session.prev_total_ms = (time.monotonic() - start) * 1e3
        except websockets.ConnectionClosed:
            pass   # a client that leaves mid-request: its result is dropped, nothing else changes
        finally:
            self.connections -= 1
            self._end_episode(session)
            sent, received = ws.protocol.close_sent, ws.protocol.close_rcvd   # either may be missing (a dropped TCP)
            self.events.emit("disconnect", peer=session.peer, session=session.id, requests=session.requests,
                             seconds=round(time.monotonic() - opened, 3),
                             close_sent=sent.code if sent else None, close_received=received.code if received else None,
                             reason=(sent and sent.reason) or (received and received.reason) or None)

    def _named_scores(self, session: Session, actions: np.ndarray, embedding: dict[str, float]) -> dict[str, float]:
        """The decision's named failure scores the config sends (``monitor_scores``: () none, None all): STAC
        against the session's previous chunk (as ``Policy`` computes it in-process) and the embedding scores the
        batcher computed; only finite values (STAC has none at an episode's first decision)."""
        wanted = self.config.monitor_scores
        if wanted == ():
            return {}
        scores = dict(embedding)
        chunk = self.policy.normalised_actions(np.asarray(actions, dtype=np.float64))
        if chunk is not None:
            previous = session.previous_chunk
            if previous is not None and previous[1].shape == chunk.shape:
                scores["stac"] = float(stac(chunk, previous[1], session.step - previous[0]))
            session.previous_chunk = (session.step, chunk)
        return {k: v for k, v in scores.items() if math.isfinite(v) and (wanted is None or k in wanted)}

    async def _pace(self, ws: ServerConnection, session: Session) -> None:
        """After a refused request: pause before reading the connection's next frame, or close it (1008)."""
        penalty = self.penalties.refused(_host(ws), time.monotonic())
        await asyncio.sleep(_pause(penalty))
        if penalty >= PENALTY_CLOSE:
            await ws.close(1008, "8 requests refused in a row; fix the client (see the text replies)")

    async def _answer(self, session: Session, message) -> dict:
        parsed = await asyncio.get_running_loop().run_in_executor(self.decoder, decode_request, message, self.schema)
        if parsed.reset or (parsed.episode is not None and parsed.episode != session.episode):
            self._new_episode(session, parsed.episode)
        reply: dict = {"episode": session.episode, "server_timing": {}}
        fed = []
        if parsed.frames:
            fed, reply["history_padded"] = session.feed(parsed.frames, parsed.step)
        reply["step"] = session.step
        # realized latents only for the monitor: without it a reply costs one decision, as in-process act
        targets = [(s, f) for s, f in fed if s in session.pending] if self.monitor is not None else []
        want_actions = bool(parsed.frames) and not parsed.observe and parsed.outcome is None
        # with the monitor, a decision of an arm with a future head also encodes its current frame: z_now, from
        # which the service scores the persistence control and nmse_ratio (one more frame in the same pass)
        want_now = want_actions and self.monitor is not None and self.policy.model.cfg.has_future_token
        if want_actions or targets:
            frames = [f for _, f in targets] + ([session.history[-1]] if want_now else [])
            actions, z_hat, latents, timing, scores = await self.batcher.submit(Work(
                list(session.history) if want_actions else None, frames, asyncio.get_running_loop().create_future()))
            reply["server_timing"].update(timing)
        else:
            actions, z_hat, latents, scores = None, None, [], {}
        z_now = latents[-1] if want_now else None
        latents = latents[:len(targets)]
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
            if self.monitor is not None:
                scores = self._named_scores(session, actions, scores)
            if self.monitor is not None and (z_hat is not None or scores):
                if z_hat is not None:
                    session.pending[session.step + self.policy.k] = (session.step, z_hat)
                self.monitor.decision(self.config.task_id or self.policy.spec.name, session.episode, session.step,
                                      self.policy.k if z_hat is not None else None, z_hat,
                                      checkpoint=self.checkpoint or None, z_now=z_now, scores=scores or None)
        session.drop_unmatched(MAX_PENDING)
        if self.monitor is not None or scored:
            reply["monitor"] = self._monitor_state(session, scored)
        if parsed.outcome is not None:   # the reply names the episode that ended; the next request starts another
            if self.monitor is not None:
                self.monitor.outcome(session.episode, parsed.outcome, length=session.step + 1)
            reply["ended"] = {"episode": session.episode, "success": parsed.outcome}
            self._new_episode(session, None)
        return reply

    # ------------------------------------------------------------ lifecycle
    def _tls_context(self) -> ssl.SSLContext | None:
        if not self.config.tls_cert:
            return None
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        ctx.load_cert_chain(self.config.tls_cert, self.config.tls_key)
        watch = type("HandshakeWatch", (_HandshakeWatch,), {"on_refused": staticmethod(
            lambda exc, peer: self.events.emit("tls_refused", peer=peer,
                                               problem=f"{getattr(exc, 'reason', None) or type(exc).__name__}: "
                                                       f"{exc}"[:300]))})
        ctx.sslobject_class = watch
        if self.config.tls_client_ca:
            ctx.load_verify_locations(cafile=self.config.tls_client_ca)
            ctx.verify_mode = ssl.CERT_REQUIRED
        return ctx

    async def serve(self) -> None:
        ctx = self._tls_context()
        if self.config.monitor_url:
            self.monitor = MonitorClient(self.config.monitor_url, self.config.monitor_key, robot=self.config.robot,
                                         max_buffer=self.config.monitor_buffer, on_result=self._on_monitor_result)
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self.batcher = Batcher(self.policy, self.config.max_batch, self.config.max_queue,
                               scores=self.monitor is not None and self.config.monitor_scores != ())
        self.batcher.start()
        try:
            async with serve(self._handler, self.config.host, self.config.port, ssl=ctx, compression=None,
                             max_size=MAX_REQUEST_BYTES, max_queue=0, create_connection=_Connection,
                             process_request=self._process_request) as server:
                self.port = next(s.getsockname()[1] for s in server.sockets if s.family in (socket.AF_INET,
                                                                                              socket.AF_INET6))
                self.ready.set()
                if self.on_ready is not None:
                    self.on_ready(self.port)
                await self._stop.wait()
        finally:
            self.batcher.task.cancel()
            self.batcher.executor.shutdown(wait=False)
            self.decoder.shutdown(wait=False)
            if self.monitor is not None and not self.monitor.close(timeout=self.config.monitor_flush_s):
                self.events.emit("stop", monitor_records_lost=self.monitor.pending,
                                 problem=f"the monitor at {self.config.monitor_url} did not take every record within "
                                         f"{self.config.monitor_flush_s} s")

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
        """Stop serving (idempotent) and wait for the serving thread, if ``start_in_thread`` started one."""
        if self._loop is not None and self._stop is not None and not self._loop.is_closed():
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
        "observation": {k: {"shape": list(sh), "dtype": dt} for k, (sh, dt) in RequestSchema.of(policy).shapes.items()},
        "obs_steps": policy.obs_steps,
        "action": {"dim": spec.action_dim, "chunk": [policy.n_action_steps, spec.action_dim], "horizon": spec.horizon,
                   "convention": "absolute" if spec.suite != "embedded" else "absolute agent target (pixels)"},
        "control_hz": spec.control_hz, "future_k": policy.k,
        "request_fields": {"episode": "str or int: a new id starts an episode", "reset": "bool: new episode",
                           "step": "int: the newest frame's episode step", "outcome": "bool: the episode's result",
                           "observe": "bool: feed frames only", "full_chunk": "bool: all H actions"},
        "monitor": None if not config.monitor_url else {"task_id": config.task_id or spec.name},
        "limits": {"max_request_bytes": MAX_REQUEST_BYTES, "max_arrays": MAX_ARRAYS, "max_maps": MAX_MAPS,
                   "max_batch": config.max_batch, "max_queue": config.max_queue,
                   "max_connections": config.max_connections},
    }


def serve_checkpoint(checkpoint: str, config: ServeConfig, device: str = "cpu", threads: int | None = None) -> None:
    """Load a checkpoint (refused unread if it is not plain data) and serve it until interrupted; the event log
    goes to stderr as JSON lines."""
    check_config(config)
    if threads:
        torch.set_num_threads(threads)
    policy = Policy.from_checkpoint(checkpoint, device=device)
    log_to_stderr()
    server = PolicyServer(policy, config, checkpoint)
    server.on_ready = lambda port: print(   # once bound: --port 0 prints the port it got
        f"jepa-policy serve: {policy.spec.name} ({policy.model.cfg.arm}, step {policy.checkpoint_step}) on "
        f"{'wss' if config.tls_cert else 'ws'}://{config.host}:{port}"
        + (" (clients need a certificate of --tls-client-ca)" if config.tls_client_ca else "")
        + (f", monitor {config.monitor_url}" if config.monitor_url else ""), flush=True)
    try:
        server.run()
    except KeyboardInterrupt:
        pass
