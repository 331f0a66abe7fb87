"""The policy server: websocket connections (auth, the connection cap, TLS), one session per robot, requests
decoded off the event loop, decisions through the batcher, the monitor inside, and the event log.

Memory is bounded before anything is read: websockets refuses a frame above ``MAX_REQUEST_BYTES`` from its header
(close code 1009), reads a connection's next frame only once the previous one is taken (``max_queue=0``), and a
connection beyond ``--max-connections`` is refused at the handshake (HTTP 503), so buffered requests stay under
about 2 x ``max_connections`` x ``MAX_REQUEST_BYTES``.

Refused requests are paced twice, so that neither reconnecting nor rotating source addresses buys a flood
anything, and a robot whose own requests are accepted is never slowed by another's:

* all peers together: refused requests draw on one budget (``RefusalBudget``: ``REFUSED_RATE`` a second, bursts of
  ``REFUSED_BURST``; a refused frame costs one more for each MiB it held). Once it is spent, a new connection's
  handshake waits until the budget has room again (at most ``BACKLOG_MAX_S``; it is never refused for it), a
  refused connection waits as long before its next frame is read, and one whose refusal would book the budget
  beyond ``BACKLOG_MAX_S`` is closed (1008);
* per connection and address: from an address's second refused request on, the refused connection's next frame is
  read only after a pause that doubles with the address's penalty (``PACE_FIRST_S`` up to ``PACE_MAX_S``; the
  penalty halves every ``PENALTY_HALF_LIFE_S``), and a connection's eighth refused request in a row closes it
  (1008).

A connection is *trusted* from its first accepted request until one is refused: it is never paused, and at the
connection cap an untrusted connection (the longest-refused first, then the oldest) is closed to let a new one in
rather than refusing the new one's handshake; when every connection is trusted, the one idle longest is closed
instead if it sent nothing for more than ``ServeConfig.idle_evict_s`` (5 s; a robot mid-episode sends a request
every ~0.1 s), so connections that were served once and then sit idle cannot lock new robots out. HTTP 503 only
when every connection is trusted and active within that bound. A robot whose one frame is wrong hears of it at
once; a client that sends junk in a loop, reconnecting or not, from one address or many, shares a few refusals a
second with every other. Requests the server itself fails on (a bug, a MemoryError) are paced the same way,
answered in one line and logged as one JSON line with the traceback as a field; so are the event loop's own errors
(an ``accept()`` out of descriptors is an ``accept_failed`` line, at most one a second, with the count of failures
it stands for).

The monitor's state is bounded: a session keeps at most ``MAX_PENDING`` predictions waiting for their target
frame (one whose target step passed unseen is dropped), and the alert state of an episode is kept only while a
session runs it.
"""
from __future__ import annotations

import asyncio
import errno
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
from jepa_policy.serve.sessions import PeerPenalties, RefusalBudget, Session
from monitor_service.client import MonitorClient
from monitor_service.scoring import nmse


PENALTY_HALF_LIFE_S = 60.0
PENALTY_CLOSE = 8           # refused requests in a row at which a connection is closed
PACE_FIRST_S = 0.05         # the pause after the second refused request; it doubles with each next one
PACE_MAX_S = 2.0
REFUSED_RATE = 5.0          # refused requests a second, all peers together (a frame costs one more per MiB) ...
REFUSED_BURST = 10.0        # ... in bursts of this many
BACKLOG_MAX_S = 2.0         # how far ahead refusals may book that budget (the longest a handshake waits for it)
TLS_HANDSHAKE_TIMEOUT_S = 10.0   # a TLS handshake not done by then is closed, and logged as tls_refused (stalled)
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


_ACCEPT_ERRNOS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
ACCEPT_LOG_EVERY_S = 1.0   # accept_failed lines: at most one a second (each counts the failures since the last)


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
    certificate, none, plain HTTP on the TLS port) calls ``on_refused`` with the reason and the peer, and so does one
    still unfinished after ``TLS_HANDSHAKE_TIMEOUT_S`` (a stalled client, which asyncio closes without a word);
    asyncio itself says nothing of either outside its debug mode."""

    on_refused = None   # set per context (``PolicyServer._tls_context``)

    def do_handshake(self):
        if not hasattr(self, "_watched"):   # the first step of this handshake: look again once its time is up
            self._watched, self._ended = True, False
            peer, started = _handshake_peer(), time.monotonic()
            asyncio.get_running_loop().call_later(TLS_HANDSHAKE_TIMEOUT_S + 0.05, self._stalled, peer, started)
        try:
            done = super().do_handshake()
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise
        except (ssl.SSLError, OSError) as exc:
            self._ended = True
            if self.on_refused is not None:
                self.on_refused(exc, _handshake_peer())
            raise
        self._ended = True
        return done

    def _stalled(self, peer: str, started: float) -> None:
        if not self._ended and self.on_refused is not None:
            self.on_refused(TimeoutError(f"the TLS handshake was not finished within {TLS_HANDSHAKE_TIMEOUT_S:g} s "
                                         f"(stalled for {time.monotonic() - started:.1f} s); the connection was "
                                         "closed"), peer)


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
        self.refusals = RefusalBudget(REFUSED_RATE, REFUSED_BURST, BACKLOG_MAX_S)
        self.batcher: Batcher | None = None
        self.decoder = ThreadPoolExecutor(max_workers=2, thread_name_prefix="jepa-serve-decode")
        self.connections = 0
        self._accept_failures, self._accept_logged = 0, -math.inf   # accept() errors not yet logged
        # admitted connections -> (trusted: a request accepted and none refused since, last refused, opened,
        # last active: its last request came or its last answer went)
        self._admitted: dict[ServerConnection, list] = {}
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
        wait = self.refusals.admit(time.monotonic())
        if wait > 0:   # refusals spent the shared budget: every new connection waits its turn, none is turned away
            await asyncio.sleep(wait)
        if self.config.api_key is not None:
            given = request.headers.get_all("Authorization")
            expected = f"Api-Key {self.config.api_key}".encode()
            if len(given) != 1 or not hmac.compare_digest(given[0].encode(), expected):
                problem = ("no Authorization header" if not given else f"{len(given)} Authorization headers"
                           if len(given) > 1 else "a wrong key")
                self.events.emit("unauthorized", peer=peer, status=401, problem=problem)
                return connection.respond(http.HTTPStatus.UNAUTHORIZED, "send one 'Authorization: Api-Key <key>' "
                                          "header with the server's key (openpi-client's api_key)\n")
        self._admitted = {c: state for c, state in self._admitted.items() if not c.transport.is_closing()}
        if len(self._admitted) >= self.config.max_connections:
            untrusted = [(state[1], -state[2], c) for c, state in self._admitted.items() if not state[0]]
            now = time.monotonic()
            idle = [(now - state[3], c) for c, state in self._admitted.items()
                    if now - state[3] > self.config.idle_evict_s]
            if not untrusted and idle:
                # a trusted connection that sent nothing for longer than a robot mid-episode ever waits (it sends a
                # request every ~0.1 s): the one idle longest makes room, so idle connections cannot lock robots out
                seconds, victim = max(idle, key=lambda item: item[0])
                self.events.emit("evicted", peer=_peer(victim), connections=len(self._admitted),
                                 limit=self.config.max_connections,
                                 problem=f"idle {seconds:.1f} s (trusted, but no request for more than "
                                         f"{self.config.idle_evict_s:g} s)")
                del self._admitted[victim]
                victim.transport.abort()
            elif not untrusted:
                self.events.emit("refused", peer=peer, status=503, connections=len(self._admitted),
                                 limit=self.config.max_connections)
                return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                          f"the server has {len(self._admitted)} connections, its limit "
                                          "(--max-connections), each serving a robot (a request within the last "
                                          f"{self.config.idle_evict_s:g} s); retry later, or raise the limit\n")
            else:   # the connection refused most recently (else the oldest not yet served) makes room for this one
                victim = max(untrusted, key=lambda item: (item[0], item[1]))[2]
                self.events.emit("evicted", peer=_peer(victim), connections=len(self._admitted),
                                 limit=self.config.max_connections, problem="no request of it was accepted yet, or "
                                                                            "its last one was refused")
                del self._admitted[victim]
                victim.transport.abort()
        opened = time.monotonic()
        self._admitted[connection] = [False, -math.inf, opened, opened]
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
            async for message in ws:
                start = time.monotonic()
                self._active(ws, math.inf)   # in flight: not idle until it is answered
                session.requests += 1
                try:
                    reply = await self._answer(session, message)
                except ServerBusy as exc:
                    self.events.emit("busy", peer=session.peer, session=session.id, queue=self.batcher.queue.qsize())
                    await ws.send(f"jepa-policy serve: {exc}")
                    self._active(ws, time.monotonic())
                    continue
                except RequestError as exc:
                    self.events.emit("rejected", peer=session.peer, session=session.id, problem=str(exc)[:300])
                    await ws.send(f"jepa-policy serve: {exc}")
                    await self._pace(ws, session, len(message))
                    self._active(ws, time.monotonic())
                    continue
                except Exception as exc:   # a bug of ours (or MemoryError): one line back, one JSON line logged
                    self.events.emit("error", peer=session.peer, session=session.id,
                                     problem=f"{type(exc).__name__}: {exc}"[:300],
                                     traceback="".join(traceback.format_exception(exc))[-4000:])
                    await ws.send(f"jepa-policy serve: the server failed on this request ({type(exc).__name__}); "
                                  "a bug of the server: report it with the server's log")
                    await self._pace(ws, session, len(message))
                    self._active(ws, time.monotonic())
                    continue
                session.refused_in_row = 0
                if ws in self._admitted:
                    self._admitted[ws][0] = True   # trusted: never paused, never evicted
                reply["server_timing"]["prev_total_ms"] = session.prev_total_ms
                await ws.send(pack(reply))
                session.prev_total_ms = (time.monotonic() - start) * 1e3
                self._active(ws, time.monotonic())
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

    def _active(self, ws: ServerConnection, now: float) -> None:
        """The connection sent a request or was answered: it is not idle (eviction at the cap)."""
        state = self._admitted.get(ws)
        if state is not None:
            state[3] = now

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

    async def _pace(self, ws: ServerConnection, session: Session, size: int) -> None:
        """After a refused request of ``size`` bytes: the connection is no longer trusted; pause before reading its
        next frame (its address's pause, or its turn in the shared budget, whichever is longer), or close it."""
        now = time.monotonic()
        session.refused_in_row += 1
        if ws in self._admitted:
            self._admitted[ws][:2] = [False, now]
        penalty = self.penalties.refused(_host(ws), now)
        turn = self.refusals.charge(now, 1.0 + size / 2**20)
        if turn is None or session.refused_in_row >= PENALTY_CLOSE:
            await ws.close(1008, f"{session.refused_in_row} requests refused in a row; fix the client (see the text "
                                 "replies)" if turn is not None else "the server is refusing too many requests from "
                                                                     "its clients; fix this one (see the text replies)")
            return
        await asyncio.sleep(max(_pause(penalty), turn))

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
        self._loop.set_exception_handler(self._loop_error)
        self._stop = asyncio.Event()
        self.batcher = Batcher(self.policy, self.config.max_batch, self.config.max_queue,
                               scores=self.monitor is not None and self.config.monitor_scores != ())
        self.batcher.start()
        try:
            tls = {"ssl_handshake_timeout": TLS_HANDSHAKE_TIMEOUT_S} if ctx is not None else {}
            async with serve(self._handler, self.config.host, self.config.port, ssl=ctx, compression=None,
                             max_size=MAX_REQUEST_BYTES, max_queue=0, create_connection=_Connection,
                             process_request=self._process_request, **tls) as server:
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

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: dict) -> None:
        """The event loop's own errors as event lines, never asyncio's tracebacks: an accept() out of descriptors
        (EMFILE: asyncio retries a second later) as ``accept_failed``, anything else as ``error``."""
        exc = context.get("exception")
        if isinstance(exc, OSError) and exc.errno in _ACCEPT_ERRNOS:
            # one line a second at most, counting the failures it stands for (each listening socket fails on its
            # own, and a flood of connections keeps them failing for as long as it lasts)
            now = time.monotonic()
            self._accept_failures += 1
            if now - self._accept_logged >= ACCEPT_LOG_EVERY_S:
                self.events.emit("accept_failed", problem=f"{context.get('message')}: {exc.strerror or exc}"[:300],
                                 errno=errno.errorcode.get(exc.errno, exc.errno), failures=self._accept_failures)
                self._accept_failures, self._accept_logged = 0, now
            return
        self.events.emit("error", problem=f"{context.get('message')}: {type(exc).__name__ if exc else ''} {exc or ''}"
                                          .strip()[:300],
                         traceback="".join(traceback.format_exception(exc))[-4000:] if exc else None)

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
