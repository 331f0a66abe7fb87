"""Who controls the robot: the one session, its token and request counter, and the liveness of its link.

A client takes control with ``hello`` and gets a random token; every later request must carry that token
and a ``seq`` above the session's last one. ``SessionKeeper.authenticate`` decides, for any decoded map from
any connection, whether it speaks for the session; a message that does not (no session, a wrong token, a
token of the wrong type or alphabet, a stale seq) is answered and counted, and changes nothing of the
session's state or of its episode.

Link liveness (docs/real_robot.md, "Lost link and the command watchdog"): the client opens a second connection,
its *link*, whose messages libzmq echoes back without the client's interpreter (``zmq.proxy`` in a thread, which
holds no GIL), and registers it with its token. The bridge pings the link every ``heartbeat_interval``; the link
is *silent* when nothing came from the session (a request, or an echo) for ``link_timeout`` seconds of the
bridge listening, and *closed* when the control connection's descriptor reports a disconnect or a notice to it
cannot be delivered. Either way it is *held*: the session and its episode are kept for ``link_grace`` seconds,
during which the command watchdog does not run (the one rule: a held session keeps its episode for exactly the
grace); a request of the same session resumes it (an echo too, after a silence), and past the grace it is
*dropped* and its client is told why when it returns. (libzmq's own ZMTP heartbeats are not used: with them
libzmq 4.3.5 aborts the process when a flooding connection closes, ``stream_engine_base.cpp:310``.)
"""
from __future__ import annotations

import hmac
import secrets
import time
from dataclasses import dataclass

from jepa_robot import protocol as P

# a session counts its requests from the hello's seq; a hello must leave room for them (not 2**63 - 1)
MAX_HELLO_SEQ = 2**62
DROPPED_REMEMBERED = 16    # connections told why their session was dropped


@dataclass
class Session:
    token: str
    identity: bytes
    client: str
    connected_at: float
    fd: int | None                  # the connection's socket descriptor (matched against disconnect events)
    envelope: list                  # [] for DEALER clients, [b""] for REQ clients
    last_seq: int = 0
    held_since: float | None = None
    last_reply: tuple[int, dict] | None = None   # (seq, reply): sent again when a reconnected client asks
    next_probe: float = 0.0                       # when a quiet session's connection is checked next
    link_identity: bytes | None = None            # the client's link connection (echoes the bridge's pings)
    last_heard: float = 0.0                       # the last message from either of its connections
    next_ping: float = 0.0
    hold_cause: str | None = None                 # "silent" or "closed"

    @property
    def held(self) -> bool:
        return self.held_since is not None


class Refused(Exception):
    """A request that does not speak for the session; ``reply`` answers it, ``counter`` counts it."""

    def __init__(self, reply: dict, counter: str, event: str | None = None):
        super().__init__(reply.get("message", ""))
        self.reply, self.counter, self.event = reply, counter, event


class SessionKeeper:
    """The controlling session and its link; pure state, no sockets (the bridge sends what it decides)."""

    def __init__(self, link_timeout: float, link_grace: float, heartbeat_interval: float):
        self.link_timeout = float(link_timeout)
        self.link_grace = float(link_grace)
        self.heartbeat_interval = float(heartbeat_interval)
        self.session: Session | None = None
        self.dropped: dict[bytes, dict] = {}   # identity -> why its session was dropped (told on return)

    # ------------------------------------------------------------ taking and giving control
    def open(self, identity: bytes, message: dict, fd: int | None, envelope: list) -> Session:
        """A ``hello``: a new session for this connection, or Refused (another client holds control)."""
        client = message.get("client")
        client = client[:200] if type(client) is str and client else "anonymous"
        s = self.session
        if s is not None and s.identity != identity:
            held = "" if s.held_since is None else (
                f"; its link is lost and its session is kept for "
                f"{max(0.0, self.link_grace - (time.monotonic() - s.held_since)):.1f}s more")
            raise Refused(P.error(P.ERR_BUSY, f"the robot is already controlled by client {s.client!r} (connected "
                                              f"{time.monotonic() - s.connected_at:.1f}s ago{held}); only one "
                                              "client may control it: close that client (env.close()) or wait "
                                              "until it disconnects"), "busy")
        seq = message.get("seq") or 0
        if seq > MAX_HELLO_SEQ:
            raise Refused(P.error(P.ERR_BAD_MESSAGE, f"hello with seq {seq} leaves no room for the session's later "
                                                     f"requests (each needs a higher seq); start at or below "
                                                     f"2**62, e.g. at 1"), "malformed")
        now = time.monotonic()
        self.session = Session(secrets.token_hex(16), identity, client, now, fd, list(envelope), last_seq=seq,
                               next_probe=now + self.link_timeout, last_heard=now, next_ping=now)
        self.dropped.pop(identity, None)
        return self.session

    def close(self) -> None:
        """The client said ``bye``: control is free."""
        self.session = None

    def _check_token(self, identity: bytes, message: dict) -> Session:
        s = self.session
        token = message.get("session")
        if s is None or type(token) is not str or not token.isascii() or not hmac.compare_digest(token, s.token):
            raise Refused(self._not_controlling(identity, message.get("seq")), "not_controlling")
        return s

    def open_link(self, identity: bytes, message: dict) -> Session:
        """A ``link`` message with the session's token: ``identity`` is the connection to ping from now on."""
        s = self._check_token(identity, message)
        if identity == s.identity:   # its messages would be taken for echoes and never read
            raise Refused(P.error(P.ERR_BAD_MESSAGE, "the link is a second connection; this one carries the "
                                                     "session's requests"), "malformed")
        s.link_identity, s.next_ping = identity, time.monotonic()
        return s

    def authenticate(self, identity: bytes, message: dict) -> Session:
        """The session this request speaks for, or Refused; a refused request changes no state here."""
        s = self._check_token(identity, message)
        seq, kind = message.get("seq"), message["type"]
        if seq is None:
            raise Refused(P.error(P.ERR_BAD_MESSAGE, f"{kind[:40]!r} needs a 'seq' above the session's last one"),
                          "malformed")
        if seq <= s.last_seq:
            raise Refused({**P.error(P.ERR_REPLAY, f"seq {seq} is not above this session's last seq {s.last_seq}: "
                                                   "a replayed or out-of-order request is never executed"),
                           "seq": seq}, "replayed",
                          event=f"refused {kind[:40]!r} with seq {seq} from client {s.client!r}: not above the "
                                f"session's last seq {s.last_seq} (replayed or out of order)")
        return s

    def accept(self, s: Session, identity: bytes, seq: int, fd: int | None, envelope: list) -> float | None:
        """Record an authenticated request; returns how long the link was held when this request resumed it."""
        s.last_seq = seq
        resumed = None
        if s.held_since is not None:
            resumed = time.monotonic() - s.held_since
            s.held_since = s.hold_cause = None
        s.identity, s.envelope = identity, envelope
        if fd is not None:
            s.fd = fd
        s.next_probe = time.monotonic() + self.link_timeout
        return resumed

    def _not_controlling(self, identity: bytes, seq) -> dict:
        dropped = self.dropped.get(identity)
        s = self.session
        if dropped is not None:
            text = (f"{dropped['message']} ({time.monotonic() - dropped['time']:.1f}s ago); call env.reconnect() "
                    "to take control again, then env.reset() for a new episode")
        elif s is not None:
            text = f"this connection does not control the robot; client {s.client!r} does"
        else:
            text = "this connection does not control the robot; no client does (reconnect with hello)"
        return {**P.error(P.ERR_NOT_CONTROLLING, text), "seq": seq if type(seq) is int else None}

    # ------------------------------------------------------------ link liveness
    def heard(self, identity: bytes, now: float) -> float | None:
        """A message arrived from ``identity``; when it is the session's, its link is alive: returns how long the
        link was held when this echo or request ends a silence (a closed connection resumes by a request)."""
        s = self.session
        if s is None or identity not in (s.identity, s.link_identity):
            return None
        s.last_heard = now
        if s.held_since is not None and s.hold_cause == "silent":
            held, s.held_since, s.hold_cause = now - s.held_since, None, None
            return held
        return None

    def silent(self, now: float, listening_since: float) -> bool:
        """Whether nothing came from the live session for ``link_timeout`` of the bridge listening (a loop busy
        in a long backend call, a homing, heard nothing and is not a silent client)."""
        s = self.session
        return s is not None and not s.held and now - max(s.last_heard, listening_since) > self.link_timeout

    def ping_due(self, now: float) -> Session | None:
        """The session when its link connection is due for a ping."""
        s = self.session
        if s is None or s.link_identity is None or now < s.next_ping:
            return None
        s.next_ping = now + self.heartbeat_interval
        return s

    def hold(self, cause: str) -> Session:
        """The session's link is lost (``cause``: "silent" or "closed"): keep the session for the grace."""
        s = self.session
        s.held_since, s.hold_cause = time.monotonic(), cause
        return s

    def disconnected(self, fd: int) -> bool:
        """A connection closed: True when it was the session's (its link is lost now)."""
        s = self.session
        return s is not None and not s.held and s.fd is not None and fd == s.fd

    def probe_due(self, now: float) -> Session | None:
        """The live session when its quiet connection is due for a probe (a notice that fails if it is gone)."""
        s = self.session
        if s is None or s.held or now < s.next_probe:
            return None
        s.next_probe = now + self.link_timeout
        return s

    def grace_over(self, now: float) -> bool:
        s = self.session
        return s is not None and s.held and now - s.held_since > self.link_grace

    def drop(self, now: float) -> tuple[Session, float]:
        """Past the grace: release control, remember why for the client's return; (session, seconds held)."""
        s = self.session
        held = now - s.held_since
        text = (f"the bridge dropped this client's session after its link was lost for {held:.1f}s (grace "
                f"{self.link_grace:.1f}s); the running episode was interrupted and the robot holds")
        self.session = None
        self.dropped[s.identity] = {"message": text, "time": now}
        while len(self.dropped) > DROPPED_REMEMBERED:
            self.dropped.pop(next(iter(self.dropped)))
        return s, held
