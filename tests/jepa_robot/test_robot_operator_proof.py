"""The operator credential never leaves the bridge's and the operator's processes, and every answer an operator with
the credential gets is proven to come from the bridge (protocol v4: challenge and response).

Each test was a finding of a hostile check: the operator client sent the credential in clear
to whatever held the operator port, so a local user who squatted it while the bridge was down (a crash restart)
stole it, released the e-stop and shut the bridge down, and meanwhile answered e-stops ``held: true`` with no
bridge at all (H1); the squatted port made the supervisor give up for good (H1); an e-stop carrying a frame
before it was refused, not pressed (L1); a credential file owned by another user was used (L3), one that became
readable by others went on being accepted (L4); ``/dev/zero`` or a FIFO as the credential file gave a traceback or
a hang (L5); a malformed ``--operator`` address a traceback (L6).
"""
from __future__ import annotations

import os
import pwd
import signal
import subprocess
import sys
import time

import msgpack
import pytest
import zmq
from robot_testkit import Impostor, raw_socket, wait_for

from jepa_robot import protocol as P
from jepa_robot.operator import (CHALLENGE_FRAME, ESTOP_FRAME, BridgeNotProven, CredentialError, OperatorClient,
                                 OperatorError, ensure_operator_secret, estop_proof, read_operator_secret,
                                 request_mac)
from jepa_robot.operator_channel import Challenges

pytestmark = pytest.mark.timeout(180)
BRIDGE = [sys.executable, "-m", "jepa_robot.cli"]


def _own_bridge(tmp_path, **config):
    """A sim bridge with a credential file of its own (tests that change the file must not touch the suite's)."""
    from jepa_robot.backends.sim import SimBackend
    from jepa_robot.bridge import BridgeConfig, RobotBridge
    from jepa_robot.safety import SafetyConfig
    secret = tmp_path / "own" / "operator.secret"
    bridge = RobotBridge(SimBackend("PushT"), SafetyConfig(link_timeout_s=2.0, command_deadline_s=60.0),
                         BridgeConfig("tcp://127.0.0.1:*", "tcp://127.0.0.1:*", operator_secret_file=str(secret),
                                      **config))
    return bridge.start(), secret


# ----------------------------------------------------------------------------- H1: an impostor on the port


def test_an_impostor_on_the_operator_port_learns_nothing_and_is_named(tmp_path, operator_secret, robot):
    _, secret = ensure_operator_secret()
    impostor = Impostor()
    try:
        with OperatorClient(impostor.address, timeout_s=5.0) as op:
            with pytest.raises(BridgeNotProven, match="could not prove it is the robot bridge.*hardware e-stop"):
                op.status()
            with pytest.raises(BridgeNotProven, match="may NOT be stopped"):
                op.estop()
            for command in (op.clear_estop, op.home, lambda: op.confirm(True), op.shutdown):
                with pytest.raises(BridgeNotProven, match="possible impostor"):
                    command()
        everything = b"".join(b"".join(parts) for parts in impostor.received)
        assert len(impostor.received) >= 10
        assert secret not in everything and bytes.fromhex(secret.decode()) not in everything, \
            "the credential reached the process holding the port"
        # the commands it captured are worth nothing at the real bridge: their challenges are not its own
        bridge = robot.bridge()
        robot.operator(bridge).estop()
        macd = [parts for parts in impostor.received if len(parts) == 2 and len(parts[0]) == 32]
        assert len(macd) == 4
        sock = raw_socket(zmq.Context.instance(), zmq.REQ, bridge.operator_endpoint)
        for parts in macd:
            sock.send_multipart(parts)
            reply = msgpack.unpackb(sock.recv_multipart()[0], raw=False)
            assert reply["code"] == "stale_challenge" and "not issued by this bridge" in reply["message"], reply
        sock.close(linger=0)
        assert bridge.estop.latched and bridge._thread.is_alive()
        # the command line: with the credential an unproven e-stop answer fails loudly; without it, it says so
        out = subprocess.run([*BRIDGE, "estop", "--operator", impostor.address], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 1 and "could not prove it is the robot bridge" in out.stderr, out
        assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr
        out = subprocess.run([*BRIDGE, "status", "--operator", impostor.address, "--operator-secret",
                              str(tmp_path / "none")], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0 and "unverified" in out.stderr, out
    finally:
        impostor.close()


def test_answers_of_the_real_bridge_are_proven(robot):
    bridge = robot.bridge()
    op = robot.operator(bridge)
    assert op.status()["verified"] is True
    answer = op.estop()
    assert answer["verified"] is True and answer["held"] is True
    op.clear_estop()
    assert not bridge.estop.latched
    with OperatorClient(bridge.operator_endpoint, secret_file="/nonexistent") as stranger:
        assert stranger.status()["verified"] is False
        assert stranger.estop()["verified"] is False and bridge.estop.latched


def test_a_captured_command_is_good_once_and_for_this_bridge_process_only(robot):
    bridge = robot.bridge()
    secret = read_operator_secret()
    sock = raw_socket(zmq.Context.instance(), zmq.REQ, bridge.operator_endpoint)

    def rpc(frames):
        sock.send_multipart(frames)
        return msgpack.unpackb(sock.recv_multipart()[0], raw=False)
    robot.operator(bridge).estop()
    nonce = rpc([CHALLENGE_FRAME])["challenge"]
    body = msgpack.packb({"v": P.PROTOCOL_VERSION, "type": "clear_estop", "challenge": nonce})
    command = [request_mac(secret, body), body]
    assert rpc(command)["type"] == "result" and not bridge.estop.latched
    robot.operator(bridge).estop()
    replayed = rpc(command)
    assert replayed["code"] == "stale_challenge" and "used before" in replayed["message"]
    assert bridge.estop.latched
    # the body is what the MAC covers: the same MAC over another body is a stranger's request
    other = msgpack.packb({"v": P.PROTOCOL_VERSION, "type": "shutdown", "challenge": nonce})
    assert rpc([command[0], other])["code"] == "unauthorized"
    sock.close(linger=0)
    assert bridge._thread.is_alive()
    # a challenge expires, and another bridge process (a restart) issued it with a key of its own
    challenges, now = Challenges(secret), time.monotonic()
    old = challenges.issue(now - 11.0)
    assert "expired" in challenges.problem(old, now)
    assert challenges.problem(challenges.issue(now), now) is None
    assert "not issued by this bridge" in Challenges(secret).problem(challenges.issue(now), now)


def test_the_supervisor_never_gives_up_on_a_busy_port(tmp_path):
    """A process holds the operator port when the bridge starts: serve exits 3 in one line, the supervisor says so
    loudly and retries, latched, until the port is free; then the bridge runs, latched (it gave up before: exit 2)."""
    from runbook_walker import free_port
    operator = f"tcp://127.0.0.1:{free_port()}"
    squatter = Impostor(operator)
    log = (tmp_path / "supervisor.log").open("w")
    sup = subprocess.Popen([*BRIDGE, "supervise", "--state-file", str(tmp_path / "state.json"), "--restart-delay",
                            "0.2", "--backend", "sim", "--task", "PushT", "--bind", "tcp://127.0.0.1:*",
                            "--operator-bind", operator, "--no-prompt"], stdout=log, stderr=subprocess.STDOUT,
                           start_new_session=True)
    try:
        wait_for(lambda: (tmp_path / "supervisor.log").read_text().count("could not bind its port") >= 2,
                 timeout_s=90, every_s=0.2)
        assert sup.poll() is None, "the supervisor gave up on a busy port"
        text = (tmp_path / "supervisor.log").read_text()
        assert "error: Address already in use" in text and "Traceback" not in text and "WARNING" in text, text
        squatter.close()
        squatter = None
        status = wait_for(lambda: _status(operator), timeout_s=120, every_s=0.3)
        assert status["verified"] and status["estop"] is True and "could not bind" in status["estop_reason"]
        with OperatorClient(operator, timeout_s=30.0) as op:
            op.shutdown()
        assert sup.wait(timeout=60) == 0
    finally:
        if squatter is not None:
            squatter.close()
        if sup.poll() is None:
            os.killpg(sup.pid, signal.SIGKILL)
        log.close()


def _status(operator: str) -> dict | None:
    try:
        with OperatorClient(operator, timeout_s=1.0) as op:
            return op.status()
    except (TimeoutError, OperatorError):
        return None


# ----------------------------------------------------------------------------- L1: the e-stop frame anywhere


@pytest.mark.parametrize("before, after", [([b"0" * 64], []), ([], [ESTOP_FRAME]), ([b"a", b"b"], []),
                                           ([b"x" * 32], [b"y"])])
def test_a_message_with_the_estop_frame_among_its_frames_is_pressed(robot, before, after):
    bridge = robot.bridge()
    sock = raw_socket(zmq.Context.instance(), zmq.REQ, bridge.operator_endpoint)
    sock.send_multipart([*before, ESTOP_FRAME, *after])
    reply = msgpack.unpackb(sock.recv_multipart()[0], raw=False)
    sock.close(linger=0)
    assert reply["type"] == "result" and reply["status"]["held"] is True, reply
    assert bridge.estop.latched


def test_an_estop_with_a_nonce_is_answered_with_its_proof(robot):
    bridge = robot.bridge()
    sock = raw_socket(zmq.Context.instance(), zmq.REQ, bridge.operator_endpoint)
    nonce = os.urandom(16)
    sock.send_multipart([ESTOP_FRAME, nonce])
    body, proof = sock.recv_multipart()
    sock.close(linger=0)
    held = msgpack.unpackb(body, raw=False)["status"]["held"]
    assert held is True and proof == estop_proof(read_operator_secret(), nonce, held)


# ----------------------------------------------------------------------------- L3-L6: the credential file


def test_a_credential_file_of_another_user_is_refused(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("giving a file to another user needs root")
    folder = tmp_path / "shared"
    folder.mkdir(mode=0o700)
    file = folder / "operator.secret"
    file.write_text("ab" * 32)
    file.chmod(0o600)
    os.chown(file, pwd.getpwnam("nobody").pw_uid, -1)
    for read in (ensure_operator_secret, read_operator_secret):
        with pytest.raises(CredentialError, match="owned by uid"):
            read(file)
    out = subprocess.run([*BRIDGE, "serve", "--backend", "sim", "--task", "PushT", "--bind", "tcp://127.0.0.1:*",
                          "--operator-bind", "tcp://127.0.0.1:*", "--operator-secret", str(file), "--no-prompt"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and "owned by uid" in out.stderr, out


def test_a_credential_file_that_is_no_regular_file_is_refused_at_once(tmp_path):
    fifo = tmp_path / "fifo.secret"
    os.mkfifo(fifo, 0o600)
    for file in (fifo, "/dev/zero", tmp_path):
        start = time.monotonic()
        with pytest.raises(CredentialError, match="not a regular file"):
            read_operator_secret(file)
        assert time.monotonic() - start < 1.0
    for file in (fifo, "/dev/zero"):
        out = subprocess.run([*BRIDGE, "serve", "--backend", "sim", "--task", "PushT", "--bind", "tcp://127.0.0.1:*",
                              "--operator-bind", "tcp://127.0.0.1:*", "--operator-secret", str(file), "--no-prompt"],
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out
        assert "not a regular file" in out.stderr and "Traceback" not in out.stderr
        out = subprocess.run([*BRIDGE, "clear-estop", "--operator", "tcp://127.0.0.1:9", "--operator-secret",
                              str(file)], capture_output=True, text=True, timeout=60)
        assert out.returncode == 1 and len(out.stderr.strip().splitlines()) == 1, out
        assert "not a regular file" in out.stderr


def test_a_credential_that_became_readable_by_others_is_refused_from_then_on(tmp_path):
    bridge, secret = _own_bridge(tmp_path)
    try:
        with OperatorClient(bridge.operator_endpoint, secret_file=secret) as op:
            op.estop()   # the client now holds the secret
            secret.chmod(0o644)
            with pytest.raises(OperatorError, match="readable by other users"):
                op.clear_estop()
            secret.chmod(0o600)
            with pytest.raises(OperatorError, match="refused from now on"):
                op.clear_estop()
            assert bridge.estop.latched and op.status()["estop"] is True
    finally:
        bridge.close()


@pytest.mark.parametrize("address", ["garbage", "ipc://", "tcp://127.0.0.1:notaport"])
def test_a_malformed_operator_address_is_one_line(address):
    out = subprocess.run([*BRIDGE, "status", "--operator", address], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and len(out.stderr.strip().splitlines()) == 1, out
    assert "not a ZeroMQ address" in out.stderr and "Traceback" not in out.stderr
