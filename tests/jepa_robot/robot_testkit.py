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
