"""Any bytes on the wire: the bridge answers or drops and counts, never exits; replays are refused; CurveZMQ.

Each of the five reported crashes is reproduced as sent by the reporter, then a seeded fuzz run throws random
framings, random msgpack and truncated arrays at both sockets, with and without a valid session. After all of
it the bridge must still be serving, and a real client must still run an episode.
"""
from __future__ import annotations

import random
import time

import msgpack
import numpy as np
import pytest
import zmq

from robot_testkit import raw_socket as _socket
from robot_testkit import recv_reply as _recv

from jepa_robot import protocol as P
from jepa_envs.real_robot.proxy import HandshakeFailed, LostControl, RealRobotEnv

pytestmark = pytest.mark.timeout(180)

FUZZ_CONTROL = 1500
FUZZ_OPERATOR = 300
FUZZ_SESSION = 1500


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def _release(robot, bridge, *sockets) -> None:
    """Fuzzed hellos may have taken control: closing the fuzzers' sockets releases it after the grace."""
    for sock in sockets:
        sock.close(linger=0)
    deadline = time.monotonic() + 10
    while robot.operator(bridge).status()["client"] is not None and time.monotonic() < deadline:
        time.sleep(0.05)


def _serving(robot, bridge) -> None:
    """The bridge thread lives, answers the operator, and a real client runs an episode."""
    assert bridge._thread is not None and bridge._thread.is_alive()
    status = robot.operator(bridge).status()
    assert status["task"] == "PushT"
    env = robot.client(bridge)
    obs, _ = env.reset(seed=3)
    assert env.step(obs["agent_pos"])[4]["executed"] == 1
    env.close()


def test_the_five_reported_crashes_get_answers(robot, ctx):
    bridge = robot.bridge()
    # 1. a two-frame message from a DEALER socket (no session needed)
    dealer = _socket(ctx, zmq.DEALER, bridge.control_endpoint)
    dealer.send_multipart([P.encode({"type": P.HELLO}), b"second frame"])
    reply = _recv(dealer)
    assert reply["code"] == P.ERR_BAD_MESSAGE and "one frame" in reply["message"]
    # 2. a REQ socket on the control port: answered through its envelope
    req = _socket(ctx, zmq.REQ, bridge.control_endpoint)
    req.send(P.encode({"type": P.STEP, "action": [1.0, 2.0]}))
    assert _recv(req)["code"] == P.ERR_NOT_CONTROLLING
    # 3. a two-frame message on the operator port (two frames are a MAC and the message) and a three-frame one
    op = _socket(ctx, zmq.REQ, bridge.operator_endpoint)
    op.send_multipart([P.encode({"type": P.OP_STATUS}), b"extra"])
    assert _recv(op)["code"] == "unauthorized"
    op.send_multipart([P.encode({"type": P.OP_STATUS}), b"extra", b"more"])
    assert "one frame" in _recv(op)["message"]
    op.send(P.encode({"type": P.OP_STATUS}))   # and the operator socket still works
    assert _recv(op)["status"]["task"] == "PushT"
    # 4, 5. the controlling client sends a list or a map as the message type
    dealer.send(P.encode({"type": P.HELLO, "client": "raw", "seq": 1}))
    token = _recv(dealer)["session"]
    for weird in ([1, 2], {"a": 1}):
        dealer.send(msgpack.packb({"v": P.PROTOCOL_VERSION, "type": weird, "session": token, "seq": 2}))
        assert "'type' must be a string" in _recv(dealer)["message"]
    dealer.send(P.encode({"type": P.BYE, "session": token, "seq": 3}))
    assert _recv(dealer)["ok"] is True
    counters = robot.operator(bridge).status()["counters"]
    assert counters["malformed"] >= 3 and counters["operator_too_many_frames"] == 1
    _serving(robot, bridge)


def _random_msgpack(rng: random.Random, depth: int = 0):
    choice = rng.randrange(9 if depth < 4 else 6)
    if choice == 0:
        return rng.randrange(-2**63, 2**64)
    if choice == 1:
        return rng.random() * 10 ** rng.randrange(-5, 40)
    if choice == 2:
        return rng.choice(["hello", "reset", "step", "chunk", "observe", "stream", "resume", "bye", "estop",
                           "", "x" * rng.randrange(200), "status", "confirm", "home", "shutdown"])
    if choice == 3:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(32)))
    if choice == 4:
        return rng.choice([None, True, False])
    if choice == 5:   # an ndarray map with a random (often wrong) dtype, shape or payload length
        dtype = rng.choice(["<f8", "<f4", "|u1", "|O", "<c16", "garbage", 7, None])
        shape = [rng.randrange(-2, 5) for _ in range(rng.randrange(4))]
        return {"__nd__": True, "dtype": dtype, "shape": shape,
                "data": bytes(rng.randrange(256) for _ in range(rng.randrange(64)))}
    if choice == 6:
        return [_random_msgpack(rng, depth + 1) for _ in range(rng.randrange(5))]
    if choice == 7:
        return {_random_key(rng): _random_msgpack(rng, depth + 1) for _ in range(rng.randrange(6))}
    return [[[[[[[[[[[]]]]]]]]]]] * rng.randrange(3)


def _random_key(rng: random.Random):
    return rng.choice(["v", "type", "seq", "session", "action", "actions", "seed", "manifest", "history",
                       "origin_step", "awaiting", "enabled", "success", "task", "client", 1, b"k"])


def _random_payload(rng: random.Random, token: str | None, seq: int) -> bytes:
    kind = rng.randrange(6)
    if kind == 0:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(64)))
    if kind == 1:   # valid msgpack, random shape
        return msgpack.packb(_random_msgpack(rng), use_bin_type=True)
    message = {_random_key(rng): _random_msgpack(rng) for _ in range(rng.randrange(6))}
    message["v"] = P.PROTOCOL_VERSION if rng.random() < 0.9 else rng.randrange(5)
    message["type"] = rng.choice(["hello", "reset", "step", "chunk", "observe", "stream", "resume", "bye",
                                  "render_images", "heartbeat", "status", "estop", "nonsense"])
    if token is not None and rng.random() < 0.9:
        message["session"] = token
    if rng.random() < 0.9:
        message["seq"] = seq
    if kind == 2:   # a plausible action of a random shape
        message["action"] = np.asarray(rng.choice([[200.0, 200.0], [1.0], [np.nan, 1.0], [[1.0, 2.0]]]))
    if kind == 3:
        message["actions"] = np.full((rng.randrange(0, 3), rng.randrange(1, 4)), rng.random() * 600)
        message["origin_step"] = rng.randrange(-1, 3)
    payload = msgpack.packb(message, default=P._encode_default, use_bin_type=True)
    if kind == 4:   # truncated
        payload = payload[:rng.randrange(max(1, len(payload)))]
    return payload


def test_fuzzed_frames_and_payloads_never_stop_the_bridge(robot, ctx):
    """A bounded, seeded fuzz run on both sockets; every request on a REQ socket gets a reply."""
    bridge = robot.bridge(command_deadline_s=60.0, link_grace_s=0.2)
    rng = random.Random(20261203)
    dealer = _socket(ctx, zmq.DEALER, bridge.control_endpoint)
    for i in range(FUZZ_CONTROL):
        frames = [_random_payload(rng, None, i) for _ in range(rng.choice([1, 1, 1, 2, 3, 0]))]
        if frames:
            dealer.send_multipart(frames)
    req_control = _socket(ctx, zmq.REQ, bridge.control_endpoint)
    operator = _socket(ctx, zmq.REQ, bridge.operator_endpoint)
    for i in range(FUZZ_OPERATOR):
        for sock in (req_control, operator):
            frames = [_random_payload(rng, None, i) for _ in range(rng.choice([1, 1, 2]))]
            if sock is operator:   # never shut the bridge down or latch the e-stop mid-run from the fuzzer
                frames = [f for f in frames if b"shutdown" not in f and b"estop" not in f] or [b"\x00"]
            sock.send_multipart(frames)
            reply = _recv(sock)   # raises zmq.Again (test failure) if nothing came back
            assert reply["type"] in (P.RESULT, P.ERROR, P.WELCOME)
    _release(robot, bridge, dealer, req_control)
    # a controlling session: random requests carrying the valid token
    session = RealRobotEnv(address=bridge.control_endpoint, client_name="fuzzer", timeout_s=20.0)
    session._request({"type": P.RESET, "seed": 0})
    raw = _socket(ctx, zmq.DEALER, bridge.control_endpoint)
    for i in range(FUZZ_SESSION):
        raw.send(_random_payload(rng, session.session, session._seq + 1 + i))
    raw.setsockopt(zmq.RCVTIMEO, 200)
    quiet_since = time.monotonic()
    while time.monotonic() - quiet_since < 1.5:   # drain the answers (link notices keep coming: skip them)
        try:
            if P.decode(raw.recv())["type"] != P.LINK:
                quiet_since = time.monotonic()
        except zmq.Again:
            pass
    session._seq += FUZZ_SESSION + 10
    try:
        session.close()
    except LostControl:
        pass
    _release(robot, bridge, raw)
    counters = bridge.status()["counters"]
    assert counters.get("malformed", 0) > 100 and counters.get("loop_errors", 0) == 0
    robot.operator(bridge).clear_estop()
    _serving(robot, bridge)


def test_replayed_or_out_of_order_requests_are_refused(robot, ctx):
    bridge = robot.bridge()
    dealer = _socket(ctx, zmq.DEALER, bridge.control_endpoint)
    dealer.send(P.encode({"type": P.HELLO, "client": "raw", "seq": 1}))
    token = _recv(dealer)["session"]
    dealer.send(P.encode({"type": P.RESET, "session": token, "seq": 2, "seed": 0}))
    obs = _recv(dealer)["obs"]
    step = P.encode({"type": P.STEP, "session": token, "seq": 3, "action": obs["agent_pos"].astype(np.float64)})
    dealer.send(step)
    assert _recv(dealer)["info"]["executed"] == 1
    dealer.send(step)   # the identical bytes again
    reply = _recv(dealer)
    assert reply["code"] == P.ERR_REPLAY and "never executed" in reply["message"]
    dealer.send(P.encode({"type": P.STEP, "session": token, "seq": 2, "action": obs["agent_pos"]}))  # older
    assert _recv(dealer)["code"] == P.ERR_REPLAY
    dealer.send(P.encode({"type": P.STEP, "session": token, "action": obs["agent_pos"]}))   # no seq at all
    assert "needs a 'seq'" in _recv(dealer)["message"]
    status = robot.operator(bridge).status()
    assert status["episode"]["steps"] == 1, "a replayed step must not move the robot"
    assert status["counters"]["replayed"] == 2
    assert [e["kind"] for e in status["events"]].count("replay") == 2


def test_curve_encrypted_link(robot, tmp_path):
    """CurveZMQ: a client with an authorised key runs an episode; one without keys never gets an answer."""
    from jepa_robot.cli import main

    keys, client = tmp_path / "keys", tmp_path / "policy-pc"
    assert main(["keys", str(keys), "--client", "policy-pc", "--client-dir", str(client)]) == 0
    bridge = robot.bridge(curve={"curve_secret_key": str(keys / "bridge.key_secret"),
                                 "curve_authorized_dir": str(keys / "authorized_clients")})
    env = robot.client(bridge, curve_server_key=str(keys / "bridge.key"),
                       curve_client_key=str(client / "policy-pc.key_secret"))
    obs, _ = env.reset(seed=0)
    assert env.step(obs["agent_pos"])[4]["executed"] == 1
    env.close()
    # each mismatch is named at once, not mistaken for a bridge that is not running
    with pytest.raises(HandshakeFailed, match="it requires CurveZMQ and this client has no keys"):
        RealRobotEnv(address=bridge.control_endpoint, timeout_s=5.0)
    assert main(["keys", str(tmp_path / "other"), "--client-only", "--client", "stranger"]) == 0
    with pytest.raises(HandshakeFailed, match="refused this client's CurveZMQ key"):
        RealRobotEnv(address=bridge.control_endpoint, timeout_s=5.0, curve_server_key=str(keys / "bridge.key"),
                     curve_client_key=str(tmp_path / "other" / "stranger.key_secret"))
    assert main(["keys", str(tmp_path / "other-bridge")]) == 0
    with pytest.raises(HandshakeFailed, match="is not the key of the bridge listening there"):
        RealRobotEnv(address=bridge.control_endpoint, timeout_s=5.0,
                     curve_server_key=str(tmp_path / "other-bridge" / "bridge.key"),
                     curve_client_key=str(client / "policy-pc.key_secret"))
    # authorising the stranger's public key on the robot computer lets it in (the bridge reads the folder when
    # it starts); its secret never went there
    assert main(["keys", str(keys), "--authorize", str(tmp_path / "other" / "stranger.key")]) == 0
    assert not (keys / "stranger.key_secret").exists()
    bridge = robot.bridge(curve={"curve_secret_key": str(keys / "bridge.key_secret"),
                                 "curve_authorized_dir": str(keys / "authorized_clients")})
    env = robot.client(bridge, curve_server_key=str(keys / "bridge.key"),
                       curve_client_key=str(tmp_path / "other" / "stranger.key_secret"))
    env.close()


def test_keys_never_leave_a_client_secret_in_the_bridge_folder(tmp_path, capsys):
    from jepa_robot.cli import main

    keys = tmp_path / "keys"
    with pytest.raises(SystemExit, match="needs --client-dir"):
        main(["keys", str(keys), "--client", "policy-pc"])
    with pytest.raises(SystemExit, match="inside the bridge's folder"):
        main(["keys", str(keys), "--client", "policy-pc", "--client-dir", str(keys / "clients")])
    assert main(["keys", str(keys), "--client", "policy-pc", "--client-dir", str(tmp_path / "out")]) == 0
    assert sorted(p.name for p in keys.rglob("*_secret")) == ["bridge.key_secret"]
    assert (keys / "authorized_clients" / "policy-pc.key").is_file()
    assert (tmp_path / "out" / "policy-pc.key_secret").stat().st_mode & 0o077 == 0
    with pytest.raises(SystemExit, match="holds a secret key"):
        main(["keys", str(keys), "--authorize", str(tmp_path / "out" / "policy-pc.key_secret")])


def test_a_link_on_the_sessions_own_connection_is_refused(robot, ctx):
    """The link must be a second connection: on the session's own one, the bridge would take every later request
    for an echo of its ping and never read it (the session would look alive and do nothing)."""
    bridge = robot.bridge()
    dealer = _socket(ctx, zmq.DEALER, bridge.control_endpoint)
    dealer.send(P.encode({"type": P.HELLO, "client": "raw", "seq": 1}))
    token = _recv(dealer)["session"]
    dealer.send(P.encode({"type": P.LINK, "session": token}))
    reply = _recv(dealer)
    assert reply["code"] == P.ERR_BAD_MESSAGE and "second connection" in reply["message"]
    dealer.send(P.encode({"type": P.RESET, "session": token, "seq": 2, "seed": 0}))
    obs = _recv(dealer)["obs"]
    dealer.send(P.encode({"type": P.STEP, "session": token, "seq": 3, "action": obs["agent_pos"].astype(np.float64)}))
    assert _recv(dealer)["info"]["executed"] == 1, "the session's requests are still read"
