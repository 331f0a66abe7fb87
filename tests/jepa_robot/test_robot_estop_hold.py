"""The e-stop's answer means held: from the moment a press is answered, no action starts until an operator clears it,
and a clear sent before a press never releases it.

An instrumented backend logs, in one global order, every action's start and end and every emergency stop; the
operator's answers are logged in the same order. With the safety check slowed to 20 ms (a real robot's checks
may take that long), a press lands between the check and ``backend.apply`` most of the time: before the motion
lock, 21 of 30 presses had an action start after the held answer.
"""
from __future__ import annotations

import random
import threading
import time

import numpy as np
import pytest

from jepa_robot.estop import EStop
from jepa_robot.load_bench import EventLog as Log
from jepa_robot.load_bench import hold_violations as _violations
from jepa_robot.load_bench import instrument as _instrument
from jepa_robot.operator import OperatorClient, OperatorError

pytestmark = pytest.mark.timeout(240)


def test_no_action_starts_after_the_held_answer_with_a_slow_safety_check(robot):
    bridge = robot.bridge()
    log = Log()
    _instrument(bridge, log, check_s=0.02)
    env = robot.client(bridge)
    op = robot.operator(bridge)
    rng = random.Random(0)
    presses = in_check = 0
    for _ in range(30):
        obs, _ = env.reset(seed=presses)
        chunk = np.tile(obs["agent_pos"], (8, 1))
        runner = threading.Thread(target=env.step_chunk, args=(chunk,))
        runner.start()
        time.sleep(rng.uniform(0.005, 0.15))
        in_check += bridge.runner.executing
        answer = op.estop()
        log.add("answered")
        assert answer["estop"] and answer["held"] and not answer["action_in_flight"]
        runner.join(timeout=20)
        assert not runner.is_alive()
        presses += 1
        op.clear_estop()
        log.add("cleared")
    assert presses == 30 and in_check >= 20, "most presses landed while a chunk ran"
    assert _violations(log.events) == []
    assert sum(kind == "stop" for _, kind in log.events) == 30


def test_a_press_waits_for_the_action_inside_apply_then_holds():
    """Deterministic: an action is inside apply when the press comes; the press's stop goes out after it ends,
    and a motion asked for after the latch is refused."""
    log = Log()
    estop = EStop(lambda: log.add("stop"))
    inside, release = threading.Event(), threading.Event()

    def action():
        with estop.motion("action") as free:
            assert free
            log.add("start")
            inside.set()
            release.wait(5)
            log.add("end")
    mover = threading.Thread(target=action)
    mover.start()
    assert inside.wait(5)
    answers = []
    presser = threading.Thread(target=lambda: answers.append(estop.press()))
    presser.start()
    time.sleep(0.02)
    assert estop.latched and presser.is_alive(), "latched at once, but the answer waits for the action"
    release.set()
    mover.join(5)
    presser.join(5)
    assert [k for _, k in log.events] == ["start", "end", "stop"]
    assert answers[0]["held"] and not answers[0]["action_in_flight"]
    with estop.motion("action") as free:
        assert not free


def test_a_hung_driver_call_does_not_delay_the_stop_and_is_reported():
    """An action stuck inside the driver: the press waits ACTION_WAIT_S at most, stops concurrently and says so."""
    from jepa_robot.estop import ACTION_WAIT_S
    estop = EStop(lambda: None)
    inside, release = threading.Event(), threading.Event()

    def action():
        with estop.motion("action"):
            inside.set()
            release.wait(5)
    mover = threading.Thread(target=action)
    mover.start()
    assert inside.wait(5)
    start = time.monotonic()
    answer = estop.press()
    elapsed = time.monotonic() - start
    release.set()
    mover.join(5)
    assert answer["held"] and answer["action_in_flight"]
    assert ACTION_WAIT_S <= elapsed < ACTION_WAIT_S + 1.0


def test_a_long_move_is_stopped_concurrently_not_waited_for():
    """A homing move holds no press back: the stop goes out while it runs, and no move starts after the latch."""
    log = Log()
    estop = EStop(lambda: log.add("stop"))
    inside, release = threading.Event(), threading.Event()

    def home():
        with estop.motion("move") as free:
            assert free
            inside.set()
            release.wait(5)
    mover = threading.Thread(target=home)
    mover.start()
    assert inside.wait(5)
    start = time.monotonic()
    answer = estop.press()
    assert time.monotonic() - start < 0.04 and answer["held"]
    assert [k for _, k in log.events] == ["stop"]
    release.set()
    mover.join(5)
    with estop.motion("move") as free:
        assert not free


def test_a_clear_releases_only_the_latch_it_was_received_against(robot):
    """A clear_estop reaches the bridge, a bystander's e-stop reaches it after (answered held), then the loop runs
    the clear: the e-stop stays latched and the operator is told to clear again (before, the earlier clear
    released the later press: 5 of 40 trials against a serve process, 256 actions then ran)."""
    bridge = robot.bridge()
    op, bystander = robot.operator(bridge), OperatorClient(bridge.operator_endpoint, secret_file="/nonexistent")
    channel = bridge._operator
    answer, arrived, go = channel.answer, threading.Event(), threading.Event()

    def held_back(message, generation):   # the loop takes its time to reach the clear
        if message["type"] == "clear_estop" and not go.is_set():
            arrived.set()
            go.wait(10)
        return answer(message, generation)
    channel.answer = held_back
    op.estop()
    box = {}
    clearing = threading.Thread(target=lambda: box.update(result=_try(op.clear_estop)))
    clearing.start()
    assert arrived.wait(10)
    assert bystander.estop()["held"] is True
    go.set()
    clearing.join(10)
    bystander.close()
    assert isinstance(box["result"], OperatorError) and box["result"].code == "pressed_since_clear", box
    assert "clear again" in str(box["result"]) and bridge.estop.latched
    op.clear_estop()   # a clear sent after the press releases it
    assert not bridge.estop.latched


def _try(call):
    try:
        return call()
    except OperatorError as exc:
        return exc


def test_every_press_starts_a_new_generation_of_the_latch():
    estop = EStop(lambda: None)
    estop.press()
    seen = estop.generation
    estop.press()   # on a latch already set
    assert estop.generation == seen + 1
    assert estop.clear(seen) is False and estop.latched
    assert estop.clear(estop.generation) is True and not estop.latched


def test_a_clear_read_before_a_press_in_the_same_turn_keeps_the_latch(robot):
    """The operator thread reads a signed clear_estop and then an e-stop in one turn (one DEALER connection, so the
    ROUTER reads them in that order; the turn is held until both are queued). The press is answered held at once
    and must stay latched: before, the clear's generation was read only after the turn's e-stops were pressed, so
    it released this later press."""
    import msgpack
    import zmq

    from jepa_robot.operator import CHALLENGE_FRAME, ESTOP_FRAME, read_operator_secret, request_mac
    from robot_testkit import raw_socket

    bridge = robot.bridge()
    op = robot.operator(bridge)
    op.estop()
    channel = bridge._operator
    serve_turn, hold, go = channel._serve_requests, threading.Event(), threading.Event()

    def held_turn():   # the real turn, started only once both messages wait on the socket
        if hold.is_set():
            go.wait(5)
        return serve_turn()
    channel._serve_requests = held_turn
    ctx = zmq.Context()
    sock = raw_socket(ctx, zmq.DEALER, bridge.operator_endpoint)
    try:
        sock.send_multipart([b"", CHALLENGE_FRAME])
        challenge = msgpack.unpackb(sock.recv_multipart()[1], raw=False)["challenge"]
        body = msgpack.packb({"v": 4, "type": "clear_estop", "challenge": challenge}, use_bin_type=True)
        hold.set()
        time.sleep(0.05)   # the challenge's turn has ended
        sock.send_multipart([b"", request_mac(read_operator_secret(), body), body])
        sock.send_multipart([b"", ESTOP_FRAME])
        time.sleep(0.2)   # both reach the ROUTER's queue for this connection, in this order
        go.set()
        press = msgpack.unpackb(sock.recv_multipart()[1], raw=False)
        clear = msgpack.unpackb(sock.recv_multipart()[1], raw=False)
    finally:
        sock.close(linger=0)
        ctx.term()
    assert press["status"]["held"] is True
    assert clear["type"] == "error" and clear["code"] == "pressed_since_clear", clear
    assert bridge.estop.latched
