"""Wire protocol between the robot bridge and its clients (ZeroMQ frames carrying msgpack maps).

Every message is one ZeroMQ frame holding one msgpack map with ``"v"`` (the protocol version) and ``"type"``
(a string). Numpy arrays travel as ``{"__nd__": True, "dtype": "<u1", "shape": [...], "data": <raw bytes>}``;
nothing is ever pickled, and object dtypes are refused on both ends. Requests that act on the robot carry a
``"seq"`` that grows within a session, so the bridge can refuse a replayed or out-of-order request. The full
message catalogue is in ``docs/real_robot.md``; the operator's side of it is spoken by the import-light
``jepa_robot.operator`` module, which holds the protocol version and the operator messages.
"""
from __future__ import annotations

import ipaddress
from typing import Any

import msgpack
import numpy as np

# the protocol version and the operator messages live in the import-light operator package (one home)
from jepa_robot.operator import (ERROR, OP_CHALLENGE, OP_CLEAR_ESTOP, OP_CONFIRM, OP_ESTOP, OP_HOME,  # noqa: F401
                                 OP_SHUTDOWN, OP_STATUS, PROTOCOL_VERSION, RESULT)

# size limits, checked before anything is decoded (decoding holds the interpreter: 64 KiB of the slowest msgpack
# takes ~3 ms). ZeroMQ closes a connection whose message is above its socket's limit before the bridge reads a
# byte of it; a chunk is a few KB, a hello a few hundred bytes, an operator command a few bytes
MAX_CONTROL_MESSAGE_BYTES = 64 * 1024
MAX_STRANGER_MESSAGE_BYTES = 16 * 1024     # from a connection that is not the session's: a hello, or a refusal
MAX_OPERATOR_MESSAGE_BYTES = 4 * 1024
MAX_SEQ = 2**63 - 1

# client -> bridge (control socket, ZeroMQ DEALER -> ROUTER)
HELLO = "hello"
RESET = "reset"
STEP = "step"
CHUNK = "chunk"
OBSERVE = "observe"      # the newest observations (observe-only mode, the asynchronous executor)
STREAM = "stream"        # asynchronous execution: replace the queue of actions still to run
RESUME = "resume"        # a reconnected connection asks again for the reply of request ``awaiting``
RENDER_IMAGES = "render_images"
BYE = "bye"
# bridge -> client
WELCOME = "welcome"
PENDING = "pending"  # reply deferred: waiting for the operator's confirmation
# bridge -> client notice (never a reply): a ping on the client's link connection (echoed back), or the state of
# the link on its control connection; clients skip it. client -> bridge: opens the session's link connection
LINK = "link"
# error codes a client can act on
ERR_VERSION = "version_mismatch"
ERR_BUSY = "busy"
ERR_NOT_CONTROLLING = "not_controlling"
ERR_BAD_MESSAGE = "bad_message"
ERR_INVALID_ACTION = "invalid_action"
ERR_ESTOP = "estop_latched"
ERR_TASK = "task_mismatch"
ERR_NO_EPISODE = "no_episode"
ERR_INTERNAL = "internal_error"
ERR_REPLAY = "replayed_or_stale"   # a seq not above the session's last one
ERR_OBSERVE_ONLY = "observe_only"  # the bridge serves observations only; actions are disabled
ERR_LOST = "request_lost"          # the request never arrived (the connection dropped first); send it again
ERR_RATE = "rate_limited"          # a connection without the session sent faster than the bridge answers strangers
ERR_PRESSED_SINCE = "pressed_since_clear"   # a clear_estop refused: the e-stop was pressed after it arrived


class ProtocolError(RuntimeError):
    """A message that does not follow the protocol (wrong version, malformed map, refused dtype)."""


class VersionMismatch(ProtocolError):
    """The peer speaks another protocol version."""


def _encode_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise ProtocolError(f"object arrays cannot be sent (dtype {obj.dtype}); convert to a numeric dtype")
        arr = np.ascontiguousarray(obj)
        return {"__nd__": True, "dtype": arr.dtype.str, "shape": list(arr.shape), "data": arr.tobytes()}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (tuple, set)):
        return list(obj)
    raise ProtocolError(f"cannot encode {type(obj).__name__}; send numbers, strings, lists, maps or numpy arrays")


def _decode_hook(obj: dict) -> Any:
    if obj.get("__nd__") is True:
        dtype = np.dtype(obj["dtype"])
        if dtype.hasobject:
            raise ProtocolError(f"refusing object dtype {dtype} on the wire")
        shape = tuple(int(s) for s in obj["shape"])
        data = obj["data"]
        expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if len(data) != expected:
            raise ProtocolError(f"array payload has {len(data)} bytes, shape {shape} of {dtype} needs {expected}")
        # copy: frombuffer views are read-only and would pin the message buffer
        return np.frombuffer(data, dtype=dtype).reshape(shape).copy()
    return obj


def encode(message: dict) -> bytes:
    """Serialise one protocol message; stamps the protocol version when the caller did not."""
    if "type" not in message:
        raise ProtocolError("every message needs a 'type'")
    message.setdefault("v", PROTOCOL_VERSION)
    return msgpack.packb(message, default=_encode_default, use_bin_type=True)


def decode(payload: bytes) -> dict:
    """Parse one protocol message; raises ProtocolError for anything that is not a versioned map."""
    try:
        message = msgpack.unpackb(payload, object_hook=_decode_hook, raw=False, strict_map_key=False)
    except ProtocolError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types for garbage input
        raise ProtocolError(f"undecodable message ({type(exc).__name__}: {exc})") from exc
    if not isinstance(message, dict) or "type" not in message or "v" not in message:
        raise ProtocolError("a message must be a map with 'v' and 'type'")
    if type(message["type"]) is not str:
        raise ProtocolError(f"'type' must be a string, got {type(message['type']).__name__}")
    seq = message.get("seq")
    if seq is not None and (type(seq) is not int or not 0 <= seq <= MAX_SEQ):
        raise ProtocolError(f"'seq' must be an integer in [0, 2**63), got {_short(seq)}")
    return message


def check_version(message: dict) -> None:
    """Raise ProtocolError naming both versions when a peer speaks another protocol version.

    Type-safe: ``v`` may be anything a peer sent (an array, a map, a huge integer); only an ``int`` equal to
    this side's version passes, and nothing else is ever compared or truth-tested.
    """
    version = message.get("v")
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise VersionMismatch(
            f"protocol version mismatch: peer speaks v{version if type(version) is int else _short(version)}, "
            f"this side speaks v{PROTOCOL_VERSION}; "
            "install the same jepa-policy-toolkit version on the robot computer and the policy computer"
        )


def is_loopback_host(host: str) -> bool:
    """Whether a host name or address (``[::1]`` bracketed or not) is reachable from this computer only: the
    one rule for the bridge's ZeroMQ endpoints and the policy server's websocket bind."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _short(value: Any) -> str:
    """A peer's value for an error message: its type, and a bounded repr."""
    try:
        text = repr(value)
    except Exception:   # a repr of hostile input must not be what fails
        text = "?"
    return f"{type(value).__name__} {text[:40]}"


def field(message: dict, key: str, kind: type | tuple[type, ...], default: Any = None) -> Any:
    """``message[key]`` when it is exactly of ``kind`` (bool is not an int here), ``default`` when absent.

    Raises ProtocolError naming the field, the type it needs and what came instead, whatever the peer sent.
    """
    if key not in message or message[key] is None:
        return default
    value = message[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if type(value) not in kinds:
        names = " or ".join(k.__name__ for k in kinds)
        raise ProtocolError(f"'{key}' must be {names}, got {_short(value)}")
    return value


def error(code: str, text: str, **extra: Any) -> dict:
    """An error reply; ``code`` is one of the ERR_* constants, ``text`` tells the user what to do."""
    return {"type": ERROR, "code": code, "message": text, **extra}
