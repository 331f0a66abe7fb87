"""The robot operator's side of the bridge, import-light: e-stop, clear, confirm, home, status, shutdown.

This package imports only ZeroMQ and msgpack (no numpy, gymnasium or torch), so ``jepa-robot-bridge estop``
starts in a few tens of milliseconds; it is also the single home of the protocol version, of the operator
messages and of the operator credential, which ``jepa_robot.protocol`` re-exports for the bridge. It
imports no other project package, and any may import it.

Anyone on the robot computer may stop the robot; only the operator may release it. ``estop`` and ``status``
are open to every local process; ``clear_estop``, ``home``, ``confirm`` and ``shutdown`` carry the operator
credential, a secret the bridge creates at start in a file only its user can read (``operator_secret_file``:
``$JEPA_ROBOT_OPERATOR_SECRET``, else ``~/.config/jepa-robot/operator.secret``), sent as the first of two
frames and compared by the bridge before it decodes anything. Where the operator socket crosses a network it
needs CurveZMQ as well (the bridge refuses a network bind without it), so the credential never travels in clear.

    from jepa_robot.operator import OperatorClient
    with OperatorClient("tcp://127.0.0.1:5556") as op:
        op.estop()
"""
from __future__ import annotations

import os
import secrets
import stat
from pathlib import Path

import msgpack
import zmq

# v3: liveness by the bridge's pings, echoed on the client's link connection (no ZMTP heartbeats: libzmq 4.3.5
# aborts on them under a flood); an operator ROUTER that answers the e-stop before anything queued
PROTOCOL_VERSION = 3

# operator -> bridge (operator socket, ZeroMQ REQ -> ROUTER); each answered with {"type": "result", ...} or error
OP_ESTOP = "estop"
OP_CLEAR_ESTOP = "clear_estop"
OP_CONFIRM = "confirm"
OP_HOME = "home"
OP_STATUS = "status"
OP_SHUTDOWN = "shutdown"
RESULT = "result"
ERROR = "error"
ERR_UNAUTHORIZED = "unauthorized"   # a command only the operator may give, without the operator's credential
DEFAULT_OPERATOR = "tcp://127.0.0.1:5556"
# the commands that need the operator credential (estop and status are open to every local process)
PRIVILEGED_COMMANDS = (OP_CLEAR_ESTOP, OP_HOME, OP_CONFIRM, OP_SHUTDOWN)
# an e-stop is recognised by these exact bytes, before anything is decoded (either key order)
ESTOP_FRAMES = frozenset(msgpack.packb(m, use_bin_type=True) for m in (
    {"v": PROTOCOL_VERSION, "type": OP_ESTOP}, {"type": OP_ESTOP, "v": PROTOCOL_VERSION}))
SECRET_ENV = "JEPA_ROBOT_OPERATOR_SECRET"
SECRET_BYTES = 32


def operator_secret_file(path: str | os.PathLike | None = None) -> Path:
    """Where the operator credential lives: ``path``, else ``$JEPA_ROBOT_OPERATOR_SECRET``, else
    ``~/.config/jepa-robot/operator.secret``."""
    chosen = path or os.environ.get(SECRET_ENV)
    return Path(chosen).expanduser() if chosen else Path.home() / ".config" / "jepa-robot" / "operator.secret"


class CredentialError(RuntimeError):
    """The operator credential is missing, unreadable, malformed or readable by others."""


def _checked_secret(file: Path) -> bytes:
    try:
        info = file.stat()
        text = file.read_bytes()
    except OSError as exc:
        raise CredentialError(f"cannot read the operator credential {file} ({exc.strerror or exc}); the bridge "
                              f"creates it when it starts: run this as the bridge's user, or pass "
                              f"--operator-secret FILE (${SECRET_ENV})") from None
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise CredentialError(f"the operator credential {file} is readable by other users (mode "
                              f"{stat.S_IMODE(info.st_mode):o}); make it private: chmod 600 {file}")
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
    its secret; CredentialError when it exists but cannot be used."""
    file = operator_secret_file(path)
    if not file.exists():
        try:
            file.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:   # another bridge made it just now: use theirs
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


class OperatorClient:
    """The operator's side: e-stop, confirm, home, status over the bridge's operator socket.

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
        self._sock = self._connect()

    def _connect(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.IMMEDIATE, 1)
        sock.setsockopt(zmq.RCVTIMEO, self.timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, self.timeout_ms)
        if self._curve:
            sock.curve_serverkey, sock.curve_publickey, sock.curve_secretkey = self._curve
        sock.connect(self.address)
        return sock

    def _credential(self, kind: str) -> bytes | None:
        """The operator secret for ``kind``: required for the privileged commands, sent with the others when
        this user has it (an authenticated command is served ahead of a flood of strangers' frames)."""
        if self._secret is None:
            try:
                self._secret = read_operator_secret(self.secret_file)
            except CredentialError as exc:
                if kind in PRIVILEGED_COMMANDS:
                    raise OperatorError(f"{kind} is the operator's: {exc}", ERR_UNAUTHORIZED) from None
                return None
        return self._secret

    def _call(self, message: dict) -> dict:
        kind = message["type"]
        if kind == OP_ESTOP:   # the exact frame the bridge presses before decoding anything
            frames = [next(iter(ESTOP_FRAMES))]
        else:
            body = msgpack.packb({"v": PROTOCOL_VERSION, **message}, use_bin_type=True)
            secret = self._credential(kind)
            frames = [body] if secret is None else [secret, body]
        try:
            self._sock.send_multipart(frames)
            reply = msgpack.unpackb(self._sock.recv(), raw=False, strict_map_key=False)
        except zmq.Again as exc:
            # the REQ socket now waits for a reply that may never come; a new one starts clean
            self._sock.close(linger=0)
            self._sock = self._connect()
            raise TimeoutError(f"no robot bridge answered {kind!r} on the operator socket {self.address} within "
                               f"{self.timeout_ms / 1000:g}s; is `jepa-robot-bridge serve` running there?") from exc
        if not isinstance(reply, dict) or reply.get("type") not in (RESULT, ERROR):
            raise OperatorError(f"the bridge sent an unexpected reply {reply!r:.200}")
        if reply["type"] == ERROR:
            raise OperatorError(f"bridge refused {kind}: {reply.get('message')}", reply.get("code"))
        return reply

    def estop(self) -> dict:
        """Latch the emergency stop: the robot holds now, mid-chunk included; no motion until cleared. Returns
        ``{"estop": True, "latched_at": <bridge's wall clock>, "held": <the backend's stop returned>, ...}``,
        answered by the bridge's e-stop path itself (``status`` then shows the interrupted episode)."""
        return self._call({"type": OP_ESTOP})["status"]

    def clear_estop(self) -> dict:
        return self._call({"type": OP_CLEAR_ESTOP})["status"]

    def confirm(self, success: bool) -> dict:
        """Confirm the episode's outcome (at budget end, or early when the goal is reached)."""
        return self._call({"type": OP_CONFIRM, "success": bool(success)})["status"]

    def home(self) -> dict:
        return self._call({"type": OP_HOME})["status"]

    def status(self) -> dict:
        return self._call({"type": OP_STATUS})["status"]

    def shutdown(self) -> None:
        self._call({"type": OP_SHUTDOWN})

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
