"""Floods no socket budget can stop: descriptors and memory (issue 45, second hostile round).

About 1,100 idle local connections (no byte sent) used up a bridge's descriptors at systemd's default limit of
1,024: libzmq then looped on accept() and every e-stop timed out (H2). One multipart message of 25,000 frames of
4,000 bytes (each under the operator socket's 4 KiB frame limit) grew the bridge by 280 MB, and eight processes
sending two each killed it (H3). The bridge now latches its e-stop before either runs out (``guard.py``), drops a
connection that never finishes its ZMTP handshake after 2 s, and reads a long message frame by frame.
"""
from __future__ import annotations

import time

import msgpack
import pytest
import zmq
from robot_testkit import idle_connections, raw_socket, wait_for

from jepa_robot.load_bench import Bridge
from jepa_robot.operator import OperatorClient, OperatorError

pytestmark = pytest.mark.timeout(180)


def _status(operator: str) -> dict | None:
    try:
        with OperatorClient(operator, timeout_s=1.0) as op:
            return op.status()
    except (TimeoutError, OperatorError):
        return None


def test_running_out_of_descriptors_latches_the_estop_and_the_operator_gets_back_in():
    """A bridge at RLIMIT_NOFILE 256 and 300 idle connections that finished the ZMTP handshake (they are never
    dropped): the e-stop latches at 75 % of the limit, naming the cause; once they close, ``status`` and
    ``clear-estop`` work again."""
    bridge = Bridge(descriptors=256)
    try:
        before = bridge.status()
        assert before["estop"] is False and before["resources"]["descriptor_limit"] == 256
        port = int(bridge.control.rsplit(":", 1)[1])
        conns = idle_connections(port, 300)
        time.sleep(1.0)
        assert len(conns) > 192, "the flood did not reach the guard's bound"
        for sock in conns:
            sock.close()
        status = wait_for(lambda: _status(bridge.operator), timeout_s=20, every_s=0.2)
        assert status["estop"] is True and "descriptors" in status["estop_reason"], status
        assert "fail-safe" in status["estop_reason"] and status["counters"]["connection_guard"] == 1
        assert bridge.alive()
        with OperatorClient(bridge.operator, timeout_s=10.0) as op:
            op.clear_estop()
            assert op.status()["estop"] is False
    finally:
        bridge.close()


def test_a_connection_that_never_greets_is_dropped_after_two_seconds(robot):
    """Raw TCP connections that send nothing (or part of a greeting) are closed by the bridge after its 2 s
    handshake limit (libzmq's default kept them 30 s)."""
    bridge = robot.bridge()
    ports = [int(e.rsplit(":", 1)[1]) for e in (bridge.control_endpoint, bridge.operator_endpoint)]
    conns = [c for port in ports for c in idle_connections(port, 10, greet=False)]
    conns[0].sendall(b"\xff\x00\x00\x00\x00\x00\x00\x00\x01")   # the start of a greeting, then nothing
    op = robot.operator(bridge)
    assert wait_for(lambda: sum(op.status()["resources"]["connections"].values()) >= 20, timeout_s=2)
    start = time.monotonic()
    for sock in conns:   # the bridge's own greeting comes first; then the close
        sock.settimeout(max(0.1, start + 5.0 - time.monotonic()))
        while sock.recv(4096):
            pass
        sock.close()
    assert time.monotonic() - start < 5.0
    assert wait_for(lambda: op.status()["resources"]["connections"] == {"control": 0, "operator": 1}, timeout_s=2)


def test_a_multipart_memory_bomb_is_read_frame_by_frame_and_the_memory_guard_latches():
    """One operator message of 25,000 frames of 4,000 bytes (95 MiB) at a bridge whose memory guard is at 250 MiB:
    libzmq buffers it whole before the bridge can read it (its memory grows about three times the bytes), so the
    guard latches the e-stop naming the cause; the message is read and dropped frame by frame and answered; the
    bridge lives on and is cleared."""
    bridge = Bridge(extra=("--max-rss-mb", "250"))
    try:
        before = bridge.status()
        assert before["resources"]["max_rss_mb"] == 250 and before["resources"]["rss_mb"] < 200, before
        ctx = zmq.Context()
        sock = raw_socket(ctx, zmq.DEALER, bridge.operator, timeout_ms=60_000)
        sock.setsockopt(zmq.SNDHWM, 0)
        part = b"\x01" * 4000
        for _ in range(24_999):
            sock.send(part, zmq.SNDMORE)
        sock.send(part)
        reply = msgpack.unpackb(sock.recv_multipart()[-1], raw=False)
        ctx.destroy(linger=0)
        assert reply["code"] == "bad_message" and "at most 2" in reply["message"], reply
        status = wait_for(lambda: _status(bridge.operator), timeout_s=20, every_s=0.2)
        assert status["estop"] is True and "memory" in status["estop_reason"], status
        assert status["counters"]["memory_guard"] == 1 and status["counters"]["operator_too_many_frames"] == 1
        assert bridge.alive()
        with OperatorClient(bridge.operator, timeout_s=10.0) as op:
            op.clear_estop()
            assert op.status()["estop"] is False
    finally:
        bridge.close()
