"""Raw ZeroMQ peers of the robot bridge, for tests that send what no well-behaved client would."""
from __future__ import annotations

import time

import zmq

from jepa_robot import protocol as P


def raw_socket(ctx: zmq.Context, kind: int, address: str, timeout_ms: int = 5000) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, timeout_ms)
    sock.connect(address)
    return sock


def recv_reply(sock: zmq.Socket) -> dict:
    """The next reply on a raw socket, skipping the bridge's link notices (clients ignore them)."""
    while True:
        message = P.decode(sock.recv())
        if message["type"] != P.LINK:
            return message


def wait_for(predicate, timeout_s: float = 5.0, every_s: float = 0.01):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every_s)
    raise AssertionError("condition not reached in time")


class Impostor:
    """A process squatting the operator port: answers like a bridge (a challenge of the right size,
    ``held: true`` to an e-stop, a status saying latched) and keeps every frame it is sent."""

    def __init__(self, address: str = "tcp://127.0.0.1:*"):
        import threading

        import msgpack
        self._msgpack = msgpack
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind(address)
        self.address = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.received: list[list[bytes]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import os
        while not self._stop.is_set():
            if not self.sock.poll(50):
                continue
            frames = self.sock.recv_multipart()
            route = frames[:2] if len(frames) >= 3 and frames[1] == b"" else frames[:1]
            parts = frames[len(route):]
            self.received.append(parts)
            try:
                kind = self._msgpack.unpackb(parts[-1], raw=False).get("type")
            except Exception:
                kind = None
            if kind == "challenge":
                reply = {"v": 4, "type": "result", "ok": True, "challenge": os.urandom(40)}
            else:
                reply = {"v": 4, "type": "result", "ok": True,
                         "status": {"estop": True, "latched_at": time.time(), "held": True, "reason": "a lie",
                                    "action_in_flight": False, "pid": 1, "events": [], "counters": {}}}
            # a proof-sized second frame, which it cannot compute
            self.sock.send_multipart([*route, self._msgpack.packb(reply), os.urandom(32)])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close(linger=0)
        self.ctx.term()


# a ZMTP 3.0 NULL greeting and a DEALER's READY: what a peer sends to finish the handshake, then nothing
ZMTP_GREETING = b"\xff" + b"\x00" * 8 + b"\x7f" + bytes([3, 0]) + b"NULL".ljust(20, b"\x00") + b"\x00" * 32
_READY = bytes([5]) + b"READY" + bytes([11]) + b"Socket-Type" + (6).to_bytes(4, "big") + b"DEALER"
ZMTP_READY = bytes([0x04, len(_READY)]) + _READY


def idle_connections(port: int, count: int, greet: bool = True, timeout_s: float = 5.0) -> list:
    """Up to ``count`` raw TCP connections to 127.0.0.1:``port`` (stopping at the first that cannot be made), each
    having finished the ZMTP handshake (``greet``) or sent nothing; the caller closes them."""
    import socket
    conns = []
    for _ in range(count):
        sock = socket.socket()
        sock.settimeout(timeout_s)
        try:
            sock.connect(("127.0.0.1", port))
            if greet:
                sock.sendall(ZMTP_GREETING + ZMTP_READY)
        except OSError:
            sock.close()
            break
        conns.append(sock)
    return conns
