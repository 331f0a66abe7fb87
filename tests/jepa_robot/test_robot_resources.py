"""Floods no socket budget can stop: descriptors and memory.

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


def test_memory_that_never_falls_back_still_trips_the_guard_again(monkeypatch):
    """After a flood the process keeps most of the memory it took (no REARM), yet a second flood after the
    operator's clear must latch again: every growth by MEMORY_STEP of the bound past the last trip's reading trips.
    The resident-memory reading is injected (the memory bomb above measures the real one); the guard, its check
    and the e-stop latch are the bridge's own."""
    from jepa_robot import guard as G
    from jepa_robot.estop import EStop

    readings = [0.0]   # the guard reads once when it is built
    monkeypatch.setattr(G, "resident_mb", lambda: readings[-1])
    ctx = zmq.Context()
    estop = EStop(lambda: None)
    g = G.ResourceGuard(ctx, {}, estop, max_rss_mb=600.0)   # not started: its checks are called here
    trips, latched = [], []
    for rss, clear_first in ((100, False), (610, False), (867, False), (900, True), (1000, False), (1020, False),
                             (1100, True), (1655, False), (300, True), (610, False)):
        if clear_first and estop.latched:
            assert estop.clear(estop.generation)
        readings.append(float(rss))
        g.check(time.monotonic())
        trips.append(g.counters["memory_guard"])
        latched.append(estop.latched)
    # 610 passes the bound; 867 >= 610 + 150 (0.25 x 600); after the clear 900 and 1000 stay under 867 + 150 and
    # 1020 passes it; after the next clear 1655 >= 1020 + 150; 300 < 360 re-arms; 610 passes the bound again
    assert trips == [0, 1, 2, 2, 2, 3, 3, 4, 4, 5]
    assert latched == [False, True, True, False, False, True, False, True, False, True]
    g.stop()
    ctx.term()


def test_the_guard_decides_a_trip_and_a_rearm_on_a_fresh_count(monkeypatch):
    """The monitors' events run behind the descriptors (fault injected: /proc/self/fd read as the test says). A flood
    trips the guard once; after it closes the guard re-arms, and the connections it left in the listen backlog, then
    accepted and counted twice (their descriptors at a resynchronisation, their accept events after it), do not
    trip it again; a second real flood does. Where the count cannot be read (at the limit itself listing
    /proc/self/fd fails), the estimate decides."""
    from jepa_robot import guard as guard_module
    from jepa_robot.estop import EStop

    fds = {"open": 26}
    monkeypatch.setattr(guard_module, "open_descriptors", lambda: fds["open"])
    ctx = zmq.Context()
    sock = ctx.socket(zmq.ROUTER)
    sock.bind_to_random_port("tcp://127.0.0.1")
    estop = EStop(lambda: None)
    guard = guard_module.ResourceGuard(ctx, {"control": sock}, estop, None)
    guard.limit = 256   # trips at 192 descriptors, re-arms under 153.6

    def trips() -> int:
        return guard.counts().get("connection_guard", 0)

    try:
        t = time.monotonic() + 10
        fds["open"], guard.connections["control"] = 26 + 200, 200
        guard.check(t)
        assert estop.latched and trips() == 1
        fds["open"], guard.connections["control"] = 26, 0     # the flood closed, its disconnects read
        guard.check(t + 0.05)
        assert guard._armed["descriptors"]
        fds["open"] = 26 + 85                                 # its backlog accepted; their events not read yet
        guard.check(t + 1.1)                                  # a resynchronisation counts their descriptors
        guard.connections["control"] = 85                     # then their accept events: the estimate reads 196
        guard.check(t + 1.15)
        assert trips() == 1 and guard._armed["descriptors"]
        fds["open"], guard.connections["control"] = 26 + 200, 285   # a second flood
        guard.check(t + 1.2)
        assert trips() == 2
        fds["open"], guard.connections["control"] = 26, 0
        guard.check(t + 2.3)
        assert guard._armed["descriptors"]
        fds["open"], guard.connections["control"] = None, 200      # at the limit: no listing; the estimate trips
        guard.check(t + 2.35)
        assert trips() == 3
    finally:
        guard.stop()
        sock.close(linger=0)
        ctx.term()
