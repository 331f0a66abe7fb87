"""The control socket's wire: ZeroMQ frames in, one decoded request out; replies out. Never raises on input.

It is also where a local flood is kept from costing the bridge: the ROUTER socket already takes one message from
each connection in turn (libzmq's fair queuing), so the session's messages are never behind more than one of
each stranger's; the bridge reads a bounded number per turn (``RobotBridge._pump``). A connection that is not
the session's (a *stranger*) is limited before any byte is decoded: a message above
``MAX_STRANGER_MESSAGE_BYTES`` is refused undecoded, and beyond ``STRANGER_RATE`` messages a second (a burst of
``STRANGER_BURST``) each gets one prepared ``rate_limited`` refusal, unread, and is counted: a message then
costs the bridge a receive and a send, never a decode. All strangers together get ``STRANGERS_BYTES_RATE`` bytes
decoded a second (bursts of ``STRANGERS_BYTES_BURST``, about half a millisecond of decoding): beyond it a
stranger's message is dropped unread and unanswered (``strangers_dropped``), so 300 connections buy no more than
one (300 connections of 16,000-byte slow-to-decode arrays, each within its own limit, used to
keep the loop decoding and the link's echoes waiting). The session's own link connection (the echo of the
bridge's pings) is never decoded at all: its arrival is what counts.

The control socket is a ROUTER: a DEALER client's message arrives as ``[identity, payload]``, a REQ client's
as ``[identity, b"", payload]`` (its envelope, which the reply must carry back). ``ControlWire.receive`` turns
whatever arrived into an ``Incoming``: either a decoded, versioned map, or the error reply that tells the
sender what was wrong with its bytes. Whatever the types inside the payload (an array where the version
should be, a map as the type, a string of any alphabet), nothing here raises and nothing here touches a
session or an episode: that is the bridge's job, after it has authenticated the sender (``sessions.py``).
"""
from __future__ import annotations

import collections
import logging
from dataclasses import dataclass, field

import zmq

from jepa_robot import protocol as P

log = logging.getLogger(__name__)


STRANGER_RATE = 1000.0     # a stranger's messages answered per second: fuzzers and scanners, not a flood
STRANGER_BURST = 200
STRANGERS_BYTES_RATE = 256 * 1024.0   # bytes a second decoded for all strangers together (a message counts >= 64)
STRANGERS_BYTES_BURST = 32 * 1024     # ... and at most this much at once: ~0.5 ms of decoding in any loop turn
REMEMBERED_STRANGERS = 4096


_RATE_LIMITED = P.encode(P.error(P.ERR_RATE, f"this connection, which does not control the robot, sent more than "
                                             f"{STRANGER_RATE:g} messages a second; its messages are refused unread"))


@dataclass
class Incoming:
    """One received control message: who sent it, and either its decoded map or why it was refused; neither
    when it was dropped unread (a stranger over its rate, or the echo on the session's link connection)."""

    identity: bytes
    envelope: list = field(default_factory=list)   # [] for DEALER clients, [b""] for REQ clients
    fd: int | None = None                          # the connection's descriptor (matched to disconnects)
    message: dict | None = None
    refusal: dict | None = None                    # the error reply when ``message`` is None

    @property
    def seq(self):
        return None if self.message is None else self.message.get("seq")


def _source_fd(frame: zmq.Frame) -> int | None:
    try:
        return int(frame.get(zmq.SRCFD))
    except (zmq.ZMQError, AttributeError, TypeError, ValueError):   # libzmq without ZMQ_SRCFD
        return None


def decode_request(payload: bytes) -> tuple[dict | None, dict | None]:
    """(message, None) for a versioned protocol map, else (None, the error reply naming the problem)."""
    try:
        message = P.decode(payload)
        P.check_version(message)
    except P.ProtocolError as exc:
        return None, P.error(P.ERR_VERSION if isinstance(exc, P.VersionMismatch) else P.ERR_BAD_MESSAGE, str(exc))
    except Exception as exc:   # decode wraps what msgpack raises; this is the belt to those braces
        return None, P.error(P.ERR_BAD_MESSAGE, f"undecodable message ({type(exc).__name__})")
    return message, None


def encode_reply(message: dict | None) -> bytes:
    """A reply's bytes, always: a reply built from a peer's values that msgpack cannot hold (or none at all)
    becomes an internal-error reply, so a socket that owes an answer always has one to send."""
    try:
        if message is None:
            raise ValueError("no reply was built")
        return P.encode(message)
    except Exception:
        log.exception("a reply could not be encoded")
        return P.encode(P.error(P.ERR_INTERNAL, "the bridge built a reply it cannot encode; see its log",
                                seq=message.get("seq") if isinstance(message, dict) else None))


class PeerBuckets:
    """A token bucket per connection (``rate`` tokens a second, bursts of ``burst``) for the ``remembered`` most
    recently heard connections (the oldest is forgotten first). The control socket's strangers and the operator
    socket's connections are limited with it."""

    def __init__(self, rate: float, burst: float, remembered: int):
        self.rate, self.burst, self.remembered = float(rate), float(burst), int(remembered)
        self._buckets: collections.OrderedDict[bytes, list[float]] = collections.OrderedDict()   # [tokens, time]

    def refilled(self, identity: bytes, now: float) -> list[float]:
        """``identity``'s bucket [tokens, time], refilled to ``now``; the caller takes a token (``[0] -= 1``)."""
        bucket = self._buckets.pop(identity, None) or [self.burst, now]
        bucket[0] = min(self.burst, bucket[0] + (now - bucket[1]) * self.rate)
        bucket[1] = now
        self._buckets[identity] = bucket   # most recent last
        while len(self._buckets) > self.remembered:
            self._buckets.popitem(last=False)
        return bucket


class ControlWire:
    """Reads requests from and writes replies to the control socket; counts what it refuses or cannot send."""

    def __init__(self, sock: zmq.Socket, counters: collections.Counter):
        self.sock = sock
        self.counters = counters
        self._strangers = PeerBuckets(STRANGER_RATE, STRANGER_BURST, REMEMBERED_STRANGERS)
        self._all_strangers = [float(STRANGERS_BYTES_BURST), 0.0]   # every stranger's decoding: [bytes, time]

    def receive(self, session: bytes | None, link: bytes | None, now: float) -> Incoming | None:
        """The next waiting message, None when none is; the ``session`` connection's is decoded, the ``link``
        connection's is not, a stranger's is limited first (module docstring)."""
        try:
            frames = self.sock.recv_multipart(zmq.NOBLOCK, copy=False)
        except zmq.Again:
            return None
        identity, parts, envelope = frames[0].bytes, frames[1:], []
        if identity == link:
            return Incoming(identity)
        if len(parts) >= 2 and len(parts[0]) == 0:   # a REQ socket: empty delimiter, then the request
            envelope, parts = [b""], parts[1:]
        if identity != session:
            over = self._over_budget(identity, len(parts[-1]) if parts else 0, now)
            if over is not None:
                self.counters[over] += 1
                if over == "rate_limited":   # this connection's own limit: told so, unread
                    self._send_payload(identity, envelope, _RATE_LIMITED, count=True)
                return Incoming(identity, envelope)   # all strangers' budget spent (a flood): dropped unread
        if len(parts) != 1:
            self.counters["malformed"] += 1
            return Incoming(identity, envelope, refusal=P.error(
                P.ERR_BAD_MESSAGE, f"a request is one frame holding one msgpack map; got {len(parts)} frames"))
        if identity != session and len(parts[0]) > P.MAX_STRANGER_MESSAGE_BYTES:
            self.counters["oversized"] += 1
            return Incoming(identity, envelope, refusal=P.error(
                P.ERR_BAD_MESSAGE, f"a message of {len(parts[0])} bytes from a connection that does not control "
                                   f"the robot; up to {P.MAX_STRANGER_MESSAGE_BYTES} are read (a hello is a few "
                                   "hundred)"))
        message, refusal = decode_request(parts[0].bytes)
        if refusal is not None:
            self.counters["malformed"] += 1
        return Incoming(identity, envelope, _source_fd(parts[0]), message, refusal)

    def _over_budget(self, identity: bytes, size: int, now: float) -> str | None:
        """None when a stranger's message may be decoded, else the counter it is refused under: its own token
        bucket (STRANGER_RATE a second, bursts of STRANGER_BURST) and one for all strangers together
        (STRANGERS_BYTES_RATE bytes a second), so no number of connections buys more decoding."""
        bucket = self._strangers.refilled(identity, now)
        if bucket[0] < 1.0:
            return "rate_limited"
        g, cost = self._all_strangers, max(size, 64)
        g[0] = min(STRANGERS_BYTES_BURST, g[0] + (now - g[1]) * STRANGERS_BYTES_RATE)
        g[1] = now
        if g[0] < cost:
            return "strangers_dropped"
        bucket[0] -= 1.0
        g[0] -= cost
        return None

    def send(self, identity: bytes, message: dict, envelope: list = (), count: bool = True) -> bool:
        """Send one message; False when the client is gone (or not reading), which is never an error here."""
        return self._send_payload(identity, envelope, encode_reply(message), count)

    def _send_payload(self, identity: bytes, envelope: list, payload: bytes, count: bool) -> bool:
        try:
            # copy=False: observations are ~150 KB with three 128x128 cameras; let ZeroMQ own the buffer
            self.sock.send_multipart([identity, *envelope, payload], flags=zmq.NOBLOCK, copy=False)
            return True
        except zmq.ZMQError:   # EHOSTUNREACH: no such connection; EAGAIN: the client stopped reading
            if count:
                self.counters["undeliverable"] += 1
            return False
