"""The robot operator's side of the bridge, import-light: e-stop, clear, confirm, home, status, shutdown.

This package imports only ZeroMQ and msgpack (no numpy, gymnasium or torch), so ``jepa-robot-bridge estop``
starts in a few tens of milliseconds; it is also the single home of the protocol version, of the operator
messages and of the operator credential, which ``jepa_robot.protocol`` re-exports for the bridge. It
imports no other project package, and any may import it.

Anyone on the robot computer may stop the robot; only the operator may release it. ``estop`` and ``status``
are open to every local process; ``clear_estop``, ``home``, ``confirm`` and ``shutdown`` need the operator
credential, a secret the bridge creates at start in a file only its user can read and owns
(``operator_secret_file``: ``$JEPA_ROBOT_OPERATOR_SECRET``, else ``~/.config/jepa-robot/operator.secret``).

The credential never leaves the bridge's and the operator's processes (protocol v4): whoever holds the
operator port learns nothing from an operator's command, and the operator learns whether the bridge answered.

* A privileged command first asks for a ``challenge`` (recognised by its exact bytes, like the e-stop, and
  answered at once): a nonce the bridge can verify without keeping state (its clock, 16 random bytes and a
  truncated HMAC under a key drawn from the secret and this process's own random bytes), valid
  ``CHALLENGE_VALID_S`` seconds, for this bridge process only, and accepted once.
* The command carries that nonce in its body (``"challenge"``) and travels as two frames: ``request_mac``
  (HMAC-SHA256 of the body under the secret) and the body.
* The bridge's reply to an authenticated command is two frames: the reply and ``reply_proof`` (an HMAC of the
  request's MAC and the reply's digest). ``OperatorClient`` checks it; a reply without it, or with a wrong one,
  raises ``BridgeNotProven``: the process on that port could not prove it is the bridge.
* ``estop`` and ``status`` may carry a 16-byte nonce of the client's (the e-stop frame followed by it; a
  ``nonce`` field of ``status``): the answer then carries ``estop_proof`` or ``status_proof``, which the
  client holding the credential checks; without the credential the answer is reported as unverified.

Where the operator socket crosses a network it needs CurveZMQ as well (the bridge refuses a network bind
without it).

    from jepa_robot.operator import OperatorClient
    with OperatorClient("tcp://127.0.0.1:5556") as op:
        op.estop()
"""
from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
from pathlib import Path

import msgpack
import zmq

# v4: operator authentication by challenge and response (the credential is never sent) and replies the bridge
# proves; v3: liveness by the bridge's pings, echoed on the client's link connection (no ZMTP heartbeats:
# libzmq 4.3.5 aborts on them under a flood); an operator ROUTER that answers the e-stop before anything queued
PROTOCOL_VERSION = 4

# operator -> bridge (operator socket, ZeroMQ REQ -> ROUTER); each answered with {"type": "result", ...} or error
OP_ESTOP = "estop"
OP_CLEAR_ESTOP = "clear_estop"
OP_CONFIRM = "confirm"
OP_HOME = "home"
OP_STATUS = "status"
OP_SHUTDOWN = "shutdown"
OP_CHALLENGE = "challenge"          # a nonce for the next privileged command
RESULT = "result"
ERROR = "error"
ERR_UNAUTHORIZED = "unauthorized"   # a command only the operator may give, without the operator's credential
ERR_CHALLENGE = "stale_challenge"   # a privileged command whose nonce expired, was used, or is not this bridge's
DEFAULT_OPERATOR = "tcp://127.0.0.1:5556"
# the commands that need the operator credential (estop and status are open to every local process)
PRIVILEGED_COMMANDS = (OP_CLEAR_ESTOP, OP_HOME, OP_CONFIRM, OP_SHUTDOWN)


def _exact(kind: str, versions: tuple[int, ...]) -> frozenset[bytes]:
    return frozenset(msgpack.packb(m, use_bin_type=True) for v in versions
                     for m in ({"v": v, "type": kind}, {"type": kind, "v": v}))


# what OperatorClient sends; the bridge recognises an e-stop by these exact bytes before anything is decoded
# (either key order), and the e-stop of an operator tool one version older too: a stop is never refused
ESTOP_FRAME = msgpack.packb({"v": PROTOCOL_VERSION, "type": OP_ESTOP}, use_bin_type=True)
ESTOP_FRAMES = _exact(OP_ESTOP, (PROTOCOL_VERSION, PROTOCOL_VERSION - 1))
CHALLENGE_FRAME = msgpack.packb({"v": PROTOCOL_VERSION, "type": OP_CHALLENGE}, use_bin_type=True)
CHALLENGE_FRAMES = _exact(OP_CHALLENGE, (PROTOCOL_VERSION,))
CHALLENGE_VALID_S = 10.0
CHALLENGE_BYTES = 40      # 8 (the bridge's clock, ms) + 16 (random) + 16 (truncated HMAC)
NONCE_BYTES = 16          # a client's nonce, sent with an e-stop or a status
MAC_BYTES = 32            # HMAC-SHA256
SECRET_ENV = "JEPA_ROBOT_OPERATOR_SECRET"
SECRET_BYTES = 32
SECRET_FILE_MAX_BYTES = 4096   # read at most this much of a credential file

# one label per kind of MAC, so that no answer of one kind is ever a valid MAC of another
_REQUEST, _REPLY, _ESTOP, _STATUS = b"jepa-robot request\0", b"jepa-robot reply\0", b"jepa-robot estop\0", \
    b"jepa-robot status\0"


def request_mac(secret: bytes, body: bytes) -> bytes:
    """The first frame of a privileged command: HMAC-SHA256 of its body under the operator credential."""
    return hmac.digest(secret, _REQUEST + body, "sha256")


def reply_proof(secret: bytes, mac: bytes, reply: bytes) -> bytes:
    """The second frame of the bridge's reply to an authenticated command (``mac``: the request's first frame)."""
    return hmac.digest(secret, _REPLY + mac + hashlib.sha256(reply).digest(), "sha256")


def estop_proof(secret: bytes, nonce: bytes, held: bool) -> bytes:
    """The second frame of the bridge's answer to an e-stop that carried the client's ``nonce``."""
    return hmac.digest(secret, _ESTOP + nonce + (b"\x01" if held else b"\x00"), "sha256")


def status_proof(secret: bytes, nonce: bytes, reply: bytes) -> bytes:
    """The second frame of the bridge's answer to a ``status`` that carried the client's ``nonce``."""
    return hmac.digest(secret, _STATUS + nonce + hashlib.sha256(reply).digest(), "sha256")


def operator_secret_file(path: str | os.PathLike | None = None) -> Path:
    """Where the operator credential lives: ``path``, else ``$JEPA_ROBOT_OPERATOR_SECRET``, else
    ``~/.config/jepa-robot/operator.secret``."""
    chosen = path or os.environ.get(SECRET_ENV)
    return Path(chosen).expanduser() if chosen else Path.home() / ".config" / "jepa-robot" / "operator.secret"


class CredentialError(RuntimeError):
    """The operator credential is missing, unreadable, malformed, not a private file of this user."""


def _fix() -> str:
    return (f"run this as the bridge's user (the credential's owner), or pass --operator-secret FILE "
            f"(${SECRET_ENV})")


def credential_problem(info: os.stat_result, file: Path) -> str | None:
    """Why a credential file with these facts may not be used, or None: it must be a regular file owned by this
    process's user and readable by no one else (another user's file could hold a secret they chose)."""
    if not stat.S_ISREG(info.st_mode):
        return (f"the operator credential {file} is not a regular file (a device, a FIFO or a folder); pass "
                f"--operator-secret with the path of a file (the bridge makes it there when it is missing)")
    if info.st_uid != os.geteuid():
        return (f"the operator credential {file} is owned by uid {info.st_uid}, not by this user (uid "
                f"{os.geteuid()}): another user could have chosen it; {_fix()}")
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        return (f"the operator credential {file} is readable by other users (mode {stat.S_IMODE(info.st_mode):o}); "
                f"make it private: chmod 600 {file}, and since it may have been read, delete it and restart the "
                "bridge to make a new one")
    return None


def _checked_secret(file: Path) -> bytes:
    """The secret in ``file``: opened without following into a FIFO's wait or a device's endless stream (the file
    type is checked on the open descriptor before a byte is read, and at most SECRET_FILE_MAX_BYTES are read)."""
    try:
        fd = os.open(file, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    except OSError as exc:
        raise CredentialError(f"cannot read the operator credential {file} ({exc.strerror or exc}); the bridge "
                              f"creates it when it starts: {_fix()}") from None
    try:
        info = os.fstat(fd)
        problem = credential_problem(info, file)
        if problem:
            raise CredentialError(problem)
        text = os.read(fd, SECRET_FILE_MAX_BYTES)
    except OSError as exc:
        raise CredentialError(f"cannot read the operator credential {file} ({exc.strerror or exc}); {_fix()}"
                              ) from None
    finally:
        os.close(fd)
    secret = text.strip()
    if len(secret) != 2 * SECRET_BYTES or any(c not in b"0123456789abcdef" for c in secret):
        raise CredentialError(f"{file} does not hold an operator credential ({2 * SECRET_BYTES} hex digits); "
                              "delete it and restart the bridge to make a new one")
    return secret


def read_operator_secret(path: str | os.PathLike | None = None) -> bytes:
    """The operator credential (CredentialError naming the file and the fix when it cannot be used)."""
    return _checked_secret(operator_secret_file(path))


def ensure_operator_secret(path: str | os.PathLike | None = None) -> tuple[Path, bytes]:
    """The bridge's side: the credential file (made now, mode 600 in a folder of mode 700, when missing) and
    its secret; CredentialError when it exists but cannot be used (another user's, shared, not a file)."""
    file = operator_secret_file(path)
    if not os.path.lexists(file):
        try:
            file.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        except FileExistsError:   # another bridge made it just now: use theirs (checked below like any other)
            pass
        except OSError as exc:
            raise CredentialError(f"cannot create the operator credential {file} ({exc.strerror or exc}); pass "
                                  f"--operator-secret FILE in a folder this user can write") from None
        else:
            with os.fdopen(fd, "wb") as f:
                f.write(secrets.token_hex(SECRET_BYTES).encode() + b"\n")
    return file, _checked_secret(file)


class OperatorError(RuntimeError):
    """The bridge refused an operator command; the message says why."""

    def __init__(self, message: str, code: str | None = None):
        super().__init__(message)
        self.code = code


class BridgeNotProven(OperatorError):
    """The process on the operator port answered without proving it is the bridge (a missing or wrong proof):
    possibly an impostor holding the port, whose e-stop answers stop nothing."""

    def __init__(self, address: str, kind: str, why: str, secret_file: object = None):
        mine = "" if secret_file is None else (f" (or the credential {secret_file} is another bridge's: pass this "
                                               "bridge's with --operator-secret)")
        super().__init__(f"the process on {address} could not prove it is the robot bridge ({why}) when asked "
                         f"{kind!r}: possible impostor holding the operator port{mine}; use the hardware e-stop, then "
                         "find who holds the port (ss -ltnp) and check the bridge's log", "unproven")


class OperatorClient:
    """The operator's side: e-stop, confirm, home, status over the bridge's operator socket.

    With the operator credential (``secret_file``, readable by this user) every answer is checked: a privileged
    command by challenge and response, an e-stop and a status by a nonce of this client's; an answer the bridge
    did not prove raises ``BridgeNotProven``. Without it, ``estop`` and ``status`` still work and their answers
    say ``"verified": False``.

    Usable for as long as it lives: a call that times out (no bridge, or one that did not answer in time) raises
    TimeoutError and leaves a fresh socket behind, so the next call (the e-stop of a long-lived tool) goes out
    at once instead of failing on the REQ socket's state. Nothing is queued while no bridge is connected
    (ZMQ_IMMEDIATE), so an e-stop that timed out is never delivered minutes later to a bridge that starts then.
    """

    def __init__(self, address: str = DEFAULT_OPERATOR, timeout_s: float = 5.0,
                 secret_file: str | os.PathLike | None = None, curve_server_key: str | None = None,
                 curve_client_key: str | None = None):
        self.address = address
        self.timeout_ms = int(timeout_s * 1000)
        self.secret_file = operator_secret_file(secret_file)
        self._secret: bytes | None = None
        self._curve = _curve_keys(curve_server_key, curve_client_key)
        self._ctx = zmq.Context()
        try:
            self._sock = self._connect()
        except zmq.ZMQError as exc:
            self._ctx.term()
            raise OperatorError(f"--operator {address!r:.200} is not a ZeroMQ address this client can connect to "
                                f"({exc}); use tcp://127.0.0.1:PORT or ipc:///PATH") from None

    def _connect(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.IMMEDIATE, 1)
        sock.setsockopt(zmq.RCVTIMEO, self.timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, self.timeout_ms)
        try:
            if self._curve:
                sock.curve_serverkey, sock.curve_publickey, sock.curve_secretkey = self._curve
            sock.connect(self.address)
        except zmq.ZMQError:
            sock.close(linger=0)
            raise
        return sock

    def _credential(self, kind: str) -> bytes | None:
        """The operator secret: required for the privileged commands, used to check the answers of the others
        when this user holds it (None: they are reported unverified)."""
        if self._secret is None:
            try:
                self._secret = read_operator_secret(self.secret_file)
            except CredentialError as exc:
                if kind in PRIVILEGED_COMMANDS:
                    raise OperatorError(f"{kind} is the operator's: {exc}", ERR_UNAUTHORIZED) from None
                return None
        return self._secret

    def _exchange(self, kind: str, frames: list[bytes]) -> list[bytes]:
        try:
            self._sock.send_multipart(frames)
            return self._sock.recv_multipart()
        except zmq.Again as exc:
            # the REQ socket now waits for a reply that may never come; a new one starts clean
            self._sock.close(linger=0)
            self._sock = self._connect()
            raise TimeoutError(f"no robot bridge answered {kind!r} on the operator socket {self.address} within "
                               f"{self.timeout_ms / 1000:g}s; is `jepa-robot-bridge serve` running there?") from exc

    def _decoded(self, kind: str, payload: bytes) -> dict:
        try:
            reply = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        except Exception:   # msgpack raises several unrelated types for garbage
            reply = None
        if not isinstance(reply, dict) or reply.get("type") not in (RESULT, ERROR):
            raise OperatorError(f"the process on {self.address} sent an unexpected reply to {kind!r}: "
                                f"{payload[:200]!r}")
        return reply

    def _refused(self, kind: str, reply: dict, proven: bool) -> OperatorError:
        text = f"bridge refused {kind}: {reply.get('message')}"
        if not proven and kind in PRIVILEGED_COMMANDS:   # the bridge proves every answer to a command with a MAC
            text += (f" (this answer carries no proof that the bridge sent it: the credential {self.secret_file} is "
                     f"not this bridge's, or the process on {self.address} is not the bridge; if the robot must "
                     "stop, use the hardware e-stop)")
        elif not proven:   # a refusal sent unread (a flood's budget) cannot be proven; it changes nothing either
            text += " (an unverified answer)"
        return OperatorError(text, reply.get("code"))

    def _privileged(self, kind: str, fields: dict) -> dict:
        """Challenge, then the command with its MAC, then the reply's proof (module docstring)."""
        secret = self._credential(kind)
        for attempt in range(2):   # a challenge that went stale in between (a busy bridge) is asked for again
            challenge = self._decoded(OP_CHALLENGE, self._exchange(kind, [CHALLENGE_FRAME])[0])
            if challenge["type"] == ERROR:
                raise self._refused(kind, challenge, proven=False)
            nonce = challenge.get("challenge")
            if type(nonce) is not bytes or len(nonce) != CHALLENGE_BYTES:
                raise BridgeNotProven(self.address, kind, "its challenge is not a v4 bridge's")
            body = msgpack.packb({"v": PROTOCOL_VERSION, "type": kind, **fields, "challenge": nonce},
                                 use_bin_type=True)
            mac = request_mac(secret, body)
            frames = self._exchange(kind, [mac, body])
            reply = self._decoded(kind, frames[0])
            proven = len(frames) == 2 and hmac.compare_digest(frames[1], reply_proof(secret, mac, frames[0]))
            if reply["type"] == ERROR:
                if proven and reply.get("code") == ERR_CHALLENGE and attempt == 0:
                    continue
                raise self._refused(kind, reply, proven)
            if not proven:
                raise BridgeNotProven(self.address, kind, "its answer carries no valid proof" if len(frames) == 2
                                      else "its answer carries no proof", self.secret_file)
            return reply
        raise AssertionError("unreachable")

    def estop(self) -> dict:
        """Latch the emergency stop: the robot holds now, mid-chunk included; no motion until cleared. Returns
        ``{"estop": True, "latched_at": <bridge's wall clock>, "held": <the backend's stop returned>,
        "verified": <the bridge proved it answered>, ...}``, answered by the bridge's e-stop path itself
        (``status`` then shows the interrupted episode). With the credential, an answer the bridge did not prove
        raises ``BridgeNotProven``."""
        secret = self._credential(OP_ESTOP)
        nonce = secrets.token_bytes(NONCE_BYTES) if secret is not None else None
        frames = self._exchange(OP_ESTOP, [ESTOP_FRAME] + ([nonce] if nonce else []))
        reply = self._decoded(OP_ESTOP, frames[0])
        if reply["type"] == ERROR:
            raise self._refused(OP_ESTOP, reply, proven=False)
        status = reply.get("status") if isinstance(reply.get("status"), dict) else {}
        if nonce is not None:
            held = status.get("held") is True
            if len(frames) != 2 or not hmac.compare_digest(frames[1], estop_proof(secret, nonce, held)):
                raise BridgeNotProven(self.address, OP_ESTOP, "the robot may NOT be stopped", self.secret_file)
        return {**status, "verified": nonce is not None}

    def status(self) -> dict:
        """The bridge's status; ``"verified"`` says whether the bridge proved it sent it (with the credential an
        unproven answer raises ``BridgeNotProven``)."""
        secret = self._credential(OP_STATUS)
        nonce = secrets.token_bytes(NONCE_BYTES) if secret is not None else None
        body = msgpack.packb({"v": PROTOCOL_VERSION, "type": OP_STATUS, **({"nonce": nonce} if nonce else {})},
                             use_bin_type=True)
        frames = self._exchange(OP_STATUS, [body])
        reply = self._decoded(OP_STATUS, frames[0])
        proven = nonce is not None and len(frames) == 2 and hmac.compare_digest(
            frames[1], status_proof(secret, nonce, frames[0]))
        if reply["type"] == ERROR:
            raise self._refused(OP_STATUS, reply, proven)
        if nonce is not None and not proven:
            raise BridgeNotProven(self.address, OP_STATUS, "its status carries no valid proof", self.secret_file)
        status = reply.get("status") if isinstance(reply.get("status"), dict) else {}
        return {**status, "verified": proven}

    def clear_estop(self) -> dict:
        return self._privileged(OP_CLEAR_ESTOP, {})["status"]

    def confirm(self, success: bool) -> dict:
        """Confirm the episode's outcome (at budget end, or early when the goal is reached)."""
        return self._privileged(OP_CONFIRM, {"success": bool(success)})["status"]

    def home(self) -> dict:
        return self._privileged(OP_HOME, {})["status"]

    def shutdown(self) -> None:
        self._privileged(OP_SHUTDOWN, {})

    def close(self) -> None:
        self._sock.close(linger=0)
        self._ctx.term()

    def __enter__(self) -> "OperatorClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _curve_keys(server_key: str | None, client_key: str | None) -> tuple[bytes, bytes, bytes] | None:
    """(server public, client public, client secret) for an operator socket behind CurveZMQ, or None."""
    if server_key is None and client_key is None:
        return None
    if server_key is None or client_key is None:
        raise OperatorError("CurveZMQ needs both --curve-server-key (the bridge's bridge.key) and "
                            "--curve-client-key (this operator's NAME.key_secret)")
    import zmq.auth
    try:
        server_public, _ = zmq.auth.load_certificate(server_key)
        public, secret = zmq.auth.load_certificate(client_key)
    except (OSError, ValueError) as exc:
        raise OperatorError(f"cannot read the CurveZMQ keys ({exc})") from None
    if secret is None:
        raise OperatorError(f"{client_key} holds no secret key; pass this operator's '.key_secret' file")
    return server_public, public, secret
