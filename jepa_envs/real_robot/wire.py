"""The control socket's wire: ZeroMQ frames in, one decoded request out; replies out. Never raises on input.

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

from jepa_envs.real_robot import protocol as P

log = logging.getLogger(__name__)


@dataclass
class Incoming:
    """One received control message: who sent it, and either its decoded map or why it was refused."""

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


class ControlWire:
    """Reads requests from and writes replies to the control socket; counts what it refuses or cannot send."""

    def __init__(self, sock: zmq.Socket, counters: collections.Counter):
        self.sock = sock
        self.counters = counters

    def receive(self) -> Incoming:
        """The next message (the socket has one waiting); malformed input comes back as a refusal."""
        frames = self.sock.recv_multipart(copy=False)
        identity, parts, envelope = frames[0].bytes, frames[1:], []
        if len(parts) >= 2 and len(parts[0]) == 0:   # a REQ socket: empty delimiter, then the request
            envelope, parts = [b""], parts[1:]
        if len(parts) != 1:
            self.counters["malformed"] += 1
            return Incoming(identity, envelope, refusal=P.error(
                P.ERR_BAD_MESSAGE, f"a request is one frame holding one msgpack map; got {len(parts)} frames"))
        message, refusal = decode_request(parts[0].bytes)
        if refusal is not None:
            self.counters["malformed"] += 1
        return Incoming(identity, envelope, _source_fd(parts[0]), message, refusal)

    def send(self, identity: bytes, message: dict, envelope: list = (), count: bool = True) -> bool:
        """Send one message; False when the client is gone (or not reading), which is never an error here."""
        payload = encode_reply(message)
        try:
            # copy=False: observations are ~150 KB with three 128x128 cameras; let ZeroMQ own the buffer
            self.sock.send_multipart([identity, *envelope, payload], flags=zmq.NOBLOCK, copy=False)
            return True
        except zmq.ZMQError:   # EHOSTUNREACH: no such connection; EAGAIN: the client stopped reading
            if count:
                self.counters["undeliverable"] += 1
            return False
