"""The bridge under local load (issue 35): an e-stop no traffic delays, a bridge no flood kills or starves.

Latencies are the benchmark's (``jepa-robot-bridge bench --load``); these tests check the behaviour that makes
them: the e-stop is answered and the robot stopped while the event loop is stuck and 50 operators' commands
wait for it; a flood of a stranger's frames (four full-speed sockets, closed mid-flood as the abort needed)
leaves the bridge alive, the controller's link up and its chunks running; a stranger's big or fast messages are
refused before they cost a decode; a client that falls silent is held, one that is busy in C is not.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zmq
from robot_testkit import raw_socket, recv_reply, wait_for

from jepa_robot import protocol as P
from jepa_robot.load_bench import Bridge, Child
from jepa_robot.wire import STRANGER_BURST
from jepa_robot.operator import OperatorClient

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def test_estop_is_answered_while_the_loop_is_stuck_and_fifty_operators_wait(robot, ctx):
    """The loop is inside a 2 s backend call and 50 operator connections each have a ``status`` waiting for it:
    the e-stop from a 51st is still answered at once, by the operator thread, which also stopped the robot; no
    action runs after it; the 50 statuses are answered once the loop is free. (Before: one operator request
    at a time, each waiting up to 5 s for the loop, so the e-stop waited behind all of them.)"""
    bridge = robot.bridge()
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    backend, original_apply = bridge.backend, bridge.backend.apply
    stops, applied_after, stuck = [], [], threading.Event()
    backend.emergency_stop = lambda: stops.append(time.monotonic())

    def slow_apply(action):
        if bridge.estop.latched:
            applied_after.append(action)
        if not stuck.is_set():
            stuck.set()
            time.sleep(2.0)   # a long driver call: the event loop is busy
        return original_apply(action)
    backend.apply = slow_apply
    chunk = threading.Thread(target=lambda: env.step_chunk(np.tile(obs["agent_pos"], (8, 1))))
    chunk.start()
    assert stuck.wait(10)
    waiting = [raw_socket(ctx, zmq.REQ, bridge.operator_endpoint) for _ in range(50)]
    for sock in waiting:
        sock.send(P.encode({"type": P.OP_STATUS}))
    time.sleep(0.3)   # every status is queued for the loop
    start = time.monotonic()
    with OperatorClient(bridge.operator_endpoint, timeout_s=1.5) as op:
        status = op.estop()
    answered = time.monotonic()
    assert status["estop"] and status["held"] and bridge.estop.latched
    assert len(stops) == 1 and start <= stops[0] <= answered
    assert chunk.is_alive(), "answered while the loop was still inside the backend's call"
    chunk.join(timeout=20)
    replies = [recv_reply(sock) for sock in waiting]
    assert all(r["type"] == P.RESULT and r["status"]["estop"] for r in replies)
    assert applied_after == []
    assert wait_for(lambda: (s := robot.operator(bridge).status())["episode"]["reason"] == "estop" and s)


def test_a_flood_neither_kills_the_bridge_nor_starves_the_controller(tmp_path):
    """A sim bridge in its own process with the default link timeout (one control period), a controller running
    chunks back to back, and three bursts of a stranger's flood (four DEALER sockets, undecodable and tokenless
    frames at full speed, closed while their pipes are full: what made libzmq 4.3.5 abort the bridge with ZMTP
    heartbeats on, about one flood in two). The bridge lives, the controller keeps its link and runs chunks
    during every burst, and an e-stop during a burst is answered."""
    bridge = Bridge()
    controller = Child("controller", bridge.control)
    try:
        controller.wait_ready()
        bursts = []
        for _ in range(3):
            flood = Child("flood", bridge.control)
            flood.wait_ready()   # connected (its start took longer than a burst at load 7: no message reached)
            time.sleep(1.5)
            bursts.append((time.time() - 1.2, time.time()))
            if not bursts[1:]:   # the e-stop during the first burst
                with OperatorClient(bridge.operator, timeout_s=5.0) as op:
                    assert op.estop()["held"] is True
                    assert op.clear_estop()["estop"] is False
            flood.finish()
            time.sleep(0.3)   # the flood's connections close: the abort came here
            assert bridge.alive(), f"the bridge died: {bridge.abort_line()}"
        status = bridge.status()
        assert status["client"] == "controller" and status["link"] == "up"
        assert not [e for e in status["events"] if e["kind"].startswith("link")], status["events"]
        # the flood reached the bridge (whether it also went past the strangers' limits depends on how fast this
        # machine lets the bridge read; the limits themselves are tested by test_strangers_are_limited_* and
        # test_many_strangers_buy_no_more_decoding_than_one)
        assert status["counters"].get("malformed", 0) + status["counters"].get("not_controlling", 0) > 0
    finally:
        chunks = np.asarray(controller.finish().get("chunks", []))
        bridge.close()
    for a, b in bursts:
        assert ((chunks > a) & (chunks < b)).sum() > 0, "the controller ran no chunk during a flood"


def test_strangers_are_limited_before_decoding_and_the_session_is_not(robot, ctx):
    """A message above the stranger limit is refused unread; one above the socket's limit closes the sender's
    connection inside libzmq; a stranger sending faster than it is answered gets the prepared refusal; the
    session's own requests are served throughout."""
    bridge = robot.bridge()
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    stranger = raw_socket(ctx, zmq.DEALER, bridge.control_endpoint)
    stranger.send(b"\x91" + b"\x00" * (P.MAX_STRANGER_MESSAGE_BYTES + 1))
    reply = recv_reply(stranger)
    assert reply["code"] == P.ERR_BAD_MESSAGE and "does not control the robot" in reply["message"]
    giant = raw_socket(ctx, zmq.DEALER, bridge.control_endpoint, timeout_ms=500)
    giant.send(b"\x00" * (P.MAX_CONTROL_MESSAGE_BYTES + 1))
    with pytest.raises(zmq.Again):
        giant.recv()
    for i in range(3 * STRANGER_BURST):
        stranger.send(P.encode({"type": P.STEP, "seq": i, "action": [1.0, 2.0]}))
    codes = [recv_reply(stranger).get("code") for _ in range(3 * STRANGER_BURST)]
    assert codes.count(P.ERR_RATE) > 0 and codes.count(P.ERR_NOT_CONTROLLING) >= STRANGER_BURST
    assert env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))[4]["executed"] == 8
    counters = robot.operator(bridge).status()["counters"]
    assert counters["oversized"] == 1 and counters["rate_limited"] == codes.count(P.ERR_RATE)
    assert bridge._control.getsockopt(zmq.HEARTBEAT_IVL) == 0, "no ZMTP heartbeats: libzmq aborts with them"


def test_a_silent_session_is_held_and_its_next_request_resumes_it(robot, ctx):
    """A session without a link connection (a raw client) that sends nothing for the link timeout is held; its
    next request resumes it. (A proxy env's link echoes the pings, so a quiet but live client is never held:
    tests/jepa_robot/test_robot_link.py.)"""
    bridge = robot.bridge(link_timeout_s=0.3, command_deadline_s=60.0)
    raw = raw_socket(ctx, zmq.DEALER, bridge.control_endpoint)
    raw.send(P.encode({"type": P.HELLO, "client": "raw", "seq": 1}))
    token = recv_reply(raw)["session"]
    op = robot.operator(bridge)
    status = wait_for(lambda: (s := op.status())["link"] == "held" and s)
    assert "no request and no echo" in [e for e in status["events"] if e["kind"] == "link_hold"][0]["message"]
    raw.send(P.encode({"type": P.OBSERVE, "session": token, "seq": 2}))
    assert recv_reply(raw)["type"] == P.RESULT
    assert [e["kind"] for e in op.status()["events"]].count("link_resumed") == 1


def _junk(items: int) -> bytes:
    """A msgpack array of ``items`` one-byte integers: valid, slow to decode (the hostile tester's payload)."""
    return b"\xdd" + items.to_bytes(4, "big") + b"\x01" * items


def test_many_strangers_buy_no_more_decoding_than_one(robot, ctx):
    """100 stranger connections each queue 10 messages of 16,000 bytes (slow to decode, each connection within
    its own rate limit): all strangers together are decoded within one budget (issue 35, F2: 300 such
    connections used to keep the loop decoding, the e-stop answered at p50 126 ms and the controller's link
    held 8 times). The rest is dropped unread; the controller keeps control and runs its chunk; an e-stop in
    the middle is answered and holds the robot."""
    from jepa_robot.wire import STRANGERS_BYTES_BURST, STRANGERS_BYTES_RATE
    bridge = robot.bridge()
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    controller = robot.operator(bridge).status()["client"]
    junk = _junk(15990)
    strangers = [raw_socket(ctx, zmq.DEALER, bridge.control_endpoint) for _ in range(100)]
    start = time.monotonic()
    for sock in strangers:
        for _ in range(10):
            sock.send(junk)
    assert env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))[4]["executed"] == 8
    with OperatorClient(bridge.operator_endpoint, timeout_s=5.0) as op:
        assert op.estop()["held"] is True
        op.clear_estop()
    counters = wait_for(lambda: (c := robot.operator(bridge).status()["counters"]).get("strangers_dropped", 0)
                        + c.get("malformed", 0) >= 1000 and c, timeout_s=20)
    elapsed = time.monotonic() - start
    decoded = counters.get("malformed", 0)
    assert decoded <= (STRANGERS_BYTES_BURST + STRANGERS_BYTES_RATE * elapsed) / len(junk) + 1, (decoded, elapsed)
    assert counters["strangers_dropped"] >= 1000 - decoded
    status = robot.operator(bridge).status()
    assert controller is not None and status["client"] == controller and status["link"] == "up"


def test_operator_flood_the_estop_is_pressed_before_the_queued_junk_is_decoded(robot, ctx):
    """100 connections queue 20 frames of 3,995 bytes each on the operator socket (under its 4 KiB limit), then
    an e-stop arrives behind them: it is pressed after at most a budget's worth of junk was decoded (issue 35,
    F3: each turn used to decode up to 256 junk requests before pressing any e-stop: p50 127 ms), and the flood
    as a whole is decoded within one budget for all connections, the rest dropped unread."""
    from jepa_robot.operator_channel import OPERATOR_BYTES_BURST, OPERATOR_BYTES_RATE
    bridge = robot.bridge()
    channel = bridge._operator
    decoded, at_press = [], []
    decode, press = channel._decode, bridge.estop.press

    def counting_decode(parts, authenticated):
        if len(parts[-1]) > 1000:
            decoded.append(1)
        return decode(parts, authenticated)

    def noting_press(*args):
        at_press.append(len(decoded))
        return press(*args)
    channel._decode, bridge.estop.press = counting_decode, noting_press
    junk = _junk(3990)
    flood = [raw_socket(ctx, zmq.DEALER, bridge.operator_endpoint) for _ in range(100)]
    start = time.monotonic()
    for sock in flood:
        for _ in range(20):
            sock.send(junk)
    with OperatorClient(bridge.operator_endpoint, timeout_s=5.0) as op:
        status = op.estop()
    assert status["estop"] and status["held"] and bridge.estop.latched
    counters = wait_for(lambda: (c := channel.counts()).get("operator_dropped", 0) + len(decoded) >= 2000 and c,
                        timeout_s=20)
    elapsed = time.monotonic() - start
    budget = (OPERATOR_BYTES_BURST + OPERATOR_BYTES_RATE * elapsed) / len(junk) + 1
    assert at_press == [at_press[0]] and at_press[0] <= budget, (at_press, budget)
    assert len(decoded) <= budget and counters["operator_dropped"] >= 2000 - len(decoded)
    with OperatorClient(bridge.operator_endpoint, timeout_s=5.0) as op:   # the socket still serves commands
        assert op.status()["estop"] is True
