"""Anyone on the robot computer may stop the robot; only the operator may release it, home it, confirm or shut
down; no local process can silence the operator socket; a supervisor never restarts a bridge unlatched.

Each was a finding of an independent hostile check: junk frames that contain ``estop`` drove the
operator thread's decode budget negative and left ``status`` unanswered for 25 s after a 5 s flood; any local
process's ``clear_estop`` released the latch; ``serve --operator-bind tcp://0.0.0.0:P`` was accepted; a
supervisor with a state file it could not write restarted the bridge unlatched; set-up errors exited 1 with a
traceback (and were retried); ``check`` printed a traceback on a file that is not UTF-8.
"""
from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest
import zmq
from robot_testkit import raw_socket, recv_reply, wait_for

from jepa_robot import protocol as P
from jepa_robot.load_bench import Child, operator_silence
from jepa_robot.operator import ESTOP_FRAMES, OperatorClient, OperatorError

pytestmark = pytest.mark.timeout(180)
BRIDGE = [sys.executable, "-m", "jepa_robot.cli"]


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def _stranger(bridge, **kwargs) -> OperatorClient:
    """An operator client of a local process that does not hold the operator's credential."""
    return OperatorClient(bridge.operator_endpoint, secret_file="/nonexistent/operator.secret", **kwargs)


# ----------------------------------------------------------------------------- who may do what


def test_any_local_process_may_press_only_the_operator_may_release(robot, tmp_path, operator_secret):
    bridge = robot.bridge()
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    # an e-stop from a process without the credential (a separate program, as an e-stop button's script would be)
    out = subprocess.run([*BRIDGE, "estop", "--operator", bridge.operator_endpoint, "--operator-secret",
                          str(tmp_path / "none")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert bridge.estop.latched
    with _stranger(bridge) as stranger:
        for command in (stranger.clear_estop, stranger.home, lambda: stranger.confirm(True), stranger.shutdown):
            with pytest.raises(OperatorError, match="operator's") as refused:
                command()
            assert refused.value.code == "unauthorized"
        assert stranger.status()["estop"] is True, "status stays open to every local process"
    # a credential of the right form that is not this bridge's
    wrong = tmp_path / "wrong.secret"
    wrong.write_text("0" * 64)
    wrong.chmod(0o600)
    with OperatorClient(bridge.operator_endpoint, secret_file=wrong) as impostor:
        with pytest.raises(OperatorError, match="not the MAC of the second.*carries no proof") as refused:
            impostor.clear_estop()
        assert refused.value.code == "unauthorized"
    # raw frames: the message alone, a first frame that is no MAC, and the credential itself (v3's bearer frame)
    raw = raw_socket(zmq.Context.instance(), zmq.REQ, bridge.operator_endpoint)
    for frames in ([P.encode({"type": P.OP_CLEAR_ESTOP})], [b"x", P.encode({"type": P.OP_CLEAR_ESTOP})],
                   [operator_secret.read_bytes().strip(), P.encode({"type": P.OP_CLEAR_ESTOP})]):
        raw.send_multipart(frames)
        assert recv_reply(raw)["code"] == "unauthorized"
    raw.close(linger=0)
    assert bridge.estop.latched, "no refused command released the latch"
    counters = robot.operator(bridge).status()["counters"]
    assert counters["operator_unauthorized"] >= 4   # the client without the file refused before sending
    with pytest.raises(Exception, match="emergency stop is latched"):
        env.reset(seed=1)
    # the operator (this user, with the credential the bridge made) releases it
    robot.operator(bridge).clear_estop()
    assert not bridge.estop.latched
    env.reset(seed=1)


def test_the_credential_file_is_private_and_a_shared_one_is_refused(robot, tmp_path, operator_secret):
    bridge = robot.bridge()
    assert bridge.operator_secret_file == str(operator_secret)
    assert stat.S_IMODE(os.stat(bridge.operator_secret_file).st_mode) == 0o600
    shared = tmp_path / "shared.secret"
    shared.write_text("ab" * 32)
    shared.chmod(0o644)
    with pytest.raises(OperatorError, match="chmod 600"):
        OperatorClient(bridge.operator_endpoint, secret_file=shared).clear_estop()
    from jepa_robot.backends.sim import SimBackend
    from jepa_robot.bridge import BridgeConfig, RobotBridge
    config = BridgeConfig("tcp://127.0.0.1:*", "tcp://127.0.0.1:*", operator_secret_file=str(shared))
    backend = SimBackend("PushT")
    try:
        with pytest.raises(ValueError, match="readable by other users"):
            RobotBridge(backend, config=config).bind()
    finally:
        backend.close()


def test_the_exact_estop_frames_are_what_the_operator_client_sends(robot, ctx):
    """The e-stop is recognised by its exact bytes; the same map with one more key is decoded and pressed too."""
    bridge = robot.bridge()
    for frame in ESTOP_FRAMES:
        sock = raw_socket(ctx, zmq.REQ, bridge.operator_endpoint)
        sock.send(frame)
        assert recv_reply(sock)["status"]["estop"] is True
        robot.operator(bridge).clear_estop()
    sock = raw_socket(ctx, zmq.REQ, bridge.operator_endpoint)
    sock.send(msgpack.packb({"v": P.PROTOCOL_VERSION, "type": "estop", "pad": "x" * 100}))
    assert recv_reply(sock)["status"]["estop"] is True and bridge.estop.latched


# ----------------------------------------------------------------------------- floods


def _status_once_answered(op: OperatorClient, within_s: float = 2.0) -> dict:
    """``status`` asked until the shared budget answers it (the flood's last frames may still spend this second's
    budget: an unauthenticated ``status`` is then refused ``rate_limited``, by design, not silenced)."""
    end = time.monotonic() + within_s
    while True:
        try:
            return op.status()
        except OperatorError as exc:
            if exc.code not in ("rate_limited", "busy") or time.monotonic() > end:
                raise
            time.sleep(0.05)


@pytest.mark.parametrize("role, seconds", [("estopjunk", 3.0), ("estopjunk64", 2.0)])
def test_no_flood_silences_the_operator(robot, role, seconds):
    """E-stop-like junk from one socket, then from 64: every ``status`` during the flood is answered (a result,
    or ``rate_limited``: never silence), the operator's authenticated command always with a result, and after
    the flood the first ``status`` is answered within 1 s."""
    bridge = robot.bridge()
    flood = Child(role, bridge.operator_endpoint)
    r = operator_silence(bridge.operator_endpoint, flood, seconds, secret_file=bridge.operator_secret_file)
    open_answers, operator_answers = r["during"]["open"]["answers"], r["during"]["operator"]["answers"]
    assert "silence" not in open_answers and set(open_answers) <= {"result", "rate_limited"}, r
    assert set(operator_answers) == {"result"}, r
    assert r["after_flood_first_answer_ms"] is not None and r["after_flood_first_answer_ms"] < 1000, r
    counters = _status_once_answered(robot.operator(bridge))["counters"]
    assert counters.get("operator_dropped", 0) + counters.get("operator_rate_limited", 0) > 0, "it was a flood"
    assert robot.operator(bridge).estop()["held"]


def test_a_flood_of_strangers_status_never_crowds_the_operator_out(robot):
    """300 connections without the credential keep 4 ``status`` each waiting for the event loop (its queue full, so
    they are answered ``busy``): the operator's authenticated commands, every 50 ms, are all answered with a result
    (before, 57-79 % of them were answered ``busy``: the queue was shared)."""
    bridge = robot.bridge()
    op = robot.operator(bridge)
    flood = Child("statusflood", bridge.operator_endpoint)
    flood.wait_ready()
    answers, end = [], time.monotonic() + 3.0
    while time.monotonic() < end:
        try:
            op.clear_estop()
            answers.append("result")
        except OperatorError as exc:
            answers.append(exc.code)
        time.sleep(0.05)
    seen = flood.finish()
    assert len(answers) >= 8 and set(answers) == {"result"}, answers
    assert seen["answers"].get("busy", 0) > 0, f"the strangers' queue never filled: {seen}"


def test_the_shared_budget_never_goes_negative(robot, ctx):
    """Frames that do not fit what is left of the shared budget are refused unread, not charged to it."""
    bridge = robot.bridge()
    channel = bridge._operator
    seen = []
    serve = channel._serve_requests

    def watched():
        refused = serve()
        # the budget and the drop count as this turn left them, read on the serving thread: waiting on the
        # channel's counter instead raced the append (the counter moves inside serve(), before this line)
        seen.append((channel._global[0], channel.counts().get("operator_dropped", 0)))
        return refused
    channel._serve_requests = watched
    socks = [raw_socket(ctx, zmq.DEALER, bridge.operator_endpoint) for _ in range(16)]
    junk = b"\x81\xa4type\xa5estop" + b"\xc1" * 3900
    for _ in range(30):
        for sock in socks:
            try:
                sock.send(junk, zmq.NOBLOCK)
            except zmq.Again:
                pass
    wait_for(lambda: seen and seen[-1][1] > 100, timeout_s=20)
    budgets = [budget for budget, _ in list(seen)]
    assert min(budgets) >= 0.0, min(budgets)


# ----------------------------------------------------------------------------- where it may listen


@pytest.mark.parametrize("address", ["tcp://0.0.0.0:{port}", "tcp://*:{port}"])
def test_a_network_operator_socket_without_curve_is_refused_by_serve_and_check(tmp_path, address):
    from runbook_walker import free_port
    address = address.format(port=free_port())
    for backend in (["--backend", "sim", "--task", "PushT"],):
        out = subprocess.run([*BRIDGE, "serve", *backend, "--bind", "tcp://127.0.0.1:*", "--operator-bind", address,
                              "--no-prompt"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 2, out
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "operator socket" in lines[0] and "CurveZMQ" in lines[0], out.stderr
    safety = tmp_path / "safety.toml"
    safety.write_text("[safety]\n")
    out = subprocess.run([*BRIDGE, "check", str(safety), "--task", "PushT", "--operator-bind", address],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and "error: operator_address: the operator socket" in out.stdout, out
    arx5 = (tmp_path / "arx5.toml")
    from pathlib import Path
    text = (Path(__file__).resolve().parents[2] / "deploy/robot/arx5_cabinet.toml").read_text()
    text = text.replace('operator_address = "tcp://127.0.0.1:5556"', f'operator_address = "{address}"')
    text = "\n".join(line for line in text.splitlines() if not line.startswith("curve_"))   # no CurveZMQ
    assert address in text
    arx5.write_text(text.replace("/var/lib/jepa-robot/episodes", str(tmp_path / "episodes")))
    out = subprocess.run([*BRIDGE, "check", str(arx5)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and "error: operator_address: the operator socket" in out.stdout, out.stdout


def test_a_network_operator_socket_speaks_curve_and_still_needs_the_credential(robot, tmp_path):
    subprocess.run([*BRIDGE, "keys", str(tmp_path / "keys"), "--client", "operator-pc", "--client-dir",
                    str(tmp_path / "clients")], check=True, capture_output=True, timeout=60)
    from jepa_robot.backends.sim import SimBackend
    from jepa_robot.bridge import BridgeConfig, RobotBridge
    from jepa_robot.safety import SafetyConfig
    config = BridgeConfig("tcp://127.0.0.1:*", "tcp://0.0.0.0:*",
                          curve_secret_key=str(tmp_path / "keys" / "bridge.key_secret"),
                          curve_authorized_dir=str(tmp_path / "keys" / "authorized_clients"))
    bridge = RobotBridge(SimBackend("PushT"), SafetyConfig(link_timeout_s=2.0, command_deadline_s=60.0), config)
    bridge.start()
    try:
        port = bridge.operator_endpoint.rsplit(":", 1)[1]
        keyed = {"curve_server_key": str(tmp_path / "keys" / "bridge.key"),
                 "curve_client_key": str(tmp_path / "clients" / "operator-pc.key_secret")}
        with OperatorClient(f"tcp://127.0.0.1:{port}", timeout_s=1.0) as plain:
            with pytest.raises(TimeoutError):
                plain.estop()   # no CurveZMQ handshake: the socket does not even answer
        with OperatorClient(f"tcp://127.0.0.1:{port}", timeout_s=10.0, **keyed) as op:
            assert op.estop()["held"] and bridge.estop.latched
            op.clear_estop()   # this user holds the credential file too
        assert not bridge.estop.latched
        with OperatorClient(f"tcp://127.0.0.1:{port}", timeout_s=10.0, secret_file=tmp_path / "none",
                            **keyed) as keyed_stranger:
            keyed_stranger.estop()
            with pytest.raises(OperatorError, match="operator's"):
                keyed_stranger.clear_estop()
        assert bridge.estop.latched
    finally:
        bridge.close()


# ----------------------------------------------------------------------------- supervision and set-up errors


def test_supervise_refuses_a_state_file_it_cannot_write(tmp_path):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    start = time.monotonic()
    out = subprocess.run([*BRIDGE, "supervise", "--state-file", str(not_a_folder / "state.json"), "--backend", "sim",
                          "--task", "PushT", "--no-prompt"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out
    assert out.stderr.strip().count("\n") == 0 and "cannot be written" in out.stderr, out.stderr
    assert time.monotonic() - start < 30 and "restart" not in out.stderr


def test_a_state_file_that_cannot_be_replaced_is_refused(tmp_path):
    """An immutable state file can be written beside but not replaced: supervise refused nothing before, recorded
    no latch, and a power cut while latched brought the bridge back unlatched. Now it exits 2 in one line."""
    state = tmp_path / "state.json"
    state.write_text('{"running": false, "estop": false}')
    if subprocess.run(["chattr", "+i", str(state)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not available here (needs root and a file system that has it)")
    try:
        out = subprocess.run([*BRIDGE, "supervise", "--state-file", str(state), "--backend", "sim", "--task", "PushT",
                              "--no-prompt"], capture_output=True, text=True, timeout=120)
    finally:
        subprocess.run(["chattr", "-i", str(state)], capture_output=True)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out
    assert "cannot be written and replaced" in out.stderr and "restart" not in out.stderr.split("(")[0]
    assert state.read_text() == '{"running": false, "estop": false}' and not (tmp_path / "state.json.tmp").exists()


def test_a_state_file_that_is_not_a_regular_file_is_refused_and_left_alone(tmp_path):
    """A FIFO (serve) or a character device (supervise; made with mknod in tmp_path, the numbers of /dev/null) as
    --state-file: before, the bridge started and replaced it with a regular file (as root, the system's /dev/null,
    hostile round 3). Now one line, exit 2, and the node is still there."""
    fifo = tmp_path / "state.fifo"
    os.mkfifo(fifo)
    cases = [(["serve"], fifo, stat.S_ISFIFO)]
    device = tmp_path / "fakenull"
    try:
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        cases.append((["supervise"], device, stat.S_ISCHR))
    except (PermissionError, OSError):   # not root: the FIFO case alone
        pass
    for command, node, kind in cases:
        out = subprocess.run([*BRIDGE, *command, "--state-file", str(node), "--backend", "sim", "--task", "PushT",
                              "--no-prompt"], capture_output=True, text=True, timeout=20)   # before: served on
        assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out
        assert "is not a regular file" in out.stderr, out.stderr
        assert kind(os.lstat(node).st_mode), f"{node} was replaced"


def test_another_users_state_file_in_a_sticky_folder_is_refused(request):
    """Another user's state file in a sticky folder such as /tmp: the check's sibling can be written, the file not
    replaced (the bridge's own user, here nobody, against root's file)."""
    if os.geteuid() != 0 or not os.path.exists("/usr/bin/python3"):
        pytest.skip("needs root (to act as another user) and /usr/bin/python3")
    import shutil
    import tempfile
    sticky = Path(tempfile.mkdtemp(prefix="jepa-sticky-", dir="/tmp"))   # reachable by nobody, as /tmp is
    sticky.chmod(0o1777)
    request.addfinalizer(lambda: shutil.rmtree(sticky, ignore_errors=True))
    state = sticky / "bridge-state.json"
    state.write_text('{"running": false, "estop": false}')
    state.chmod(0o666)
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    code = (f"import sys; sys.path.insert(0, {root!r}); from jepa_robot.estop import EStop\n"
            f"try:\n    EStop(lambda: None, {str(state)!r}).check_state_file()\nexcept OSError as e:\n"
            "    print('refused:', e)\nelse:\n    print('accepted')")
    out = subprocess.run(["su", "-s", "/bin/sh", "nobody", "-c", f"/usr/bin/python3 -c \"{code}\""],
                         capture_output=True, text=True, timeout=60, cwd="/")
    assert out.stdout.startswith("refused:") and "cannot be written and replaced" in out.stdout, out
    assert state.read_text() == '{"running": false, "estop": false}'


def test_a_restart_after_a_crash_is_latched_even_without_the_state_file(tmp_path):
    """kill -9 of the bridge after its state file was lost: the supervisor still restarts it latched."""
    from runbook_walker import free_port
    operator = f"tcp://127.0.0.1:{free_port()}"
    state = tmp_path / "state.json"
    log = (tmp_path / "supervisor.log").open("w")
    sup = subprocess.Popen([*BRIDGE, "supervise", "--state-file", str(state), "--restart-delay", "0.2",
                            "--backend", "sim", "--task", "PushT", "--bind", "tcp://127.0.0.1:*",
                            "--operator-bind", operator, "--no-prompt"], stdout=log, stderr=subprocess.STDOUT,
                           start_new_session=True)
    try:
        with OperatorClient(operator, timeout_s=60.0) as op:
            first = op.status()
            assert first["estop"] is False
            state.unlink()   # the record of "running" is gone (a disk that lost it)
            os.kill(first["pid"], signal.SIGKILL)
            status = wait_for(lambda: (s := _status(operator)) and s["pid"] != first["pid"] and s, timeout_s=90,
                              every_s=0.3)
            assert status["estop"] is True and "restarted by the supervisor" in status["estop_reason"]
            assert "SIGKILL" in status["estop_reason"]
            op.shutdown()
        assert sup.wait(timeout=60) == 0
    finally:
        if sup.poll() is None:
            os.killpg(sup.pid, signal.SIGKILL)
        log.close()


def _status(operator: str) -> dict | None:
    try:
        with OperatorClient(operator, timeout_s=1.0) as op:
            return op.status()
    except (TimeoutError, OperatorError):
        return None


def test_setup_errors_exit_2_in_one_line(tmp_path):
    long_path = str(tmp_path / ("x" * 5000))
    out = subprocess.run([*BRIDGE, "serve", "--backend", "sim", "--task", "PushT", "--config", long_path,
                          "--no-prompt"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out
    assert "Traceback" not in out.stderr and "too long" in out.stderr
    binary = tmp_path / "setup.toml"
    binary.write_bytes(b"[safety]\nmax_step_delta = 1\n\xff\xfe\x00junk")
    for command in (["check", str(binary), "--task", "PushT"],
                    ["serve", "--backend", "sim", "--task", "PushT", "--config", str(binary), "--no-prompt"]):
        out = subprocess.run([*BRIDGE, *command], capture_output=True, text=True, timeout=120)
        text = out.stdout + out.stderr
        assert out.returncode in (1, 2) and "Traceback" not in text and "UTF-8" in text, text
        assert len(text.strip().splitlines()) == 1, text


def test_the_estop_path_runs_at_the_real_time_priority_asked_for(tmp_path):
    """--rt-priority puts the operator thread (and the context's I/O threads) at SCHED_FIFO; a priority this
    process may not take, or one out of range, is refused before anything starts (one line, exit 2)."""
    out = subprocess.run([*BRIDGE, "serve", "--backend", "sim", "--task", "PushT", "--rt-priority", "0",
                          "--no-prompt"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and "--rt-priority" in out.stderr
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except PermissionError:
        pytest.skip("this user may not take real-time priorities (CAP_SYS_NICE / RLIMIT_RTPRIO)")
    from jepa_robot.backends.sim import SimBackend
    from jepa_robot.bridge import BridgeConfig, RobotBridge
    bridge = RobotBridge(SimBackend("PushT"), config=BridgeConfig("tcp://127.0.0.1:*", "tcp://127.0.0.1:*",
                                                                   rt_priority=10))
    bridge.start()
    try:
        tid = wait_for(lambda: bridge._operator._thread is not None and bridge._operator._thread.native_id)
        assert wait_for(lambda: os.sched_getscheduler(tid) == os.SCHED_FIFO, timeout_s=5)
        assert os.sched_getparam(tid).sched_priority == 10
        assert os.sched_getscheduler(0) == os.SCHED_OTHER, "the caller's thread is back at normal priority"
        with OperatorClient(bridge.operator_endpoint) as op:
            assert op.estop()["held"]
    finally:
        bridge.close()


def test_a_status_read_in_the_same_turn_as_a_refusal_counts_that_refusal(robot, ctx, monkeypatch):
    """A message of too many frames and two statuses sent right behind it on one socket are read in one turn of
    the operator channel. The refusal is counted before the turn's requests are handed to the bridge's loop, so the
    first status already shows it. Before, the counters were added after the whole turn: the loop could answer a
    status of that turn first (seen once under load, in the memory-bomb test). The turn is held here on its last
    request, as a preempted operator thread would be, to make that order certain."""
    bridge = robot.bridge()
    channel = bridge._operator
    checks = []
    real = channel._peer_over_rate

    def held_on_the_second(identity, now):
        checks.append(identity)
        if len(checks) == 2:
            time.sleep(0.5)   # the loop answers the first status meanwhile
        return real(identity, now)

    monkeypatch.setattr(channel, "_peer_over_rate", held_on_the_second)
    raw = raw_socket(ctx, zmq.DEALER, bridge.operator_endpoint)
    status = P.encode({"type": P.OP_STATUS})
    raw.send_multipart([b"a", b"b", b"c"])
    raw.send_multipart([status])
    raw.send_multipart([status])
    time.sleep(0.2)   # all three wait before the channel's next turn reads them
    refusal = recv_reply(raw)
    assert refusal["code"] == "bad_message" and "at most 2" in refusal["message"], refusal
    first = recv_reply(raw)
    assert first["type"] == P.RESULT and first["ok"], first
    assert first["status"]["counters"]["operator_too_many_frames"] == 1, first
    assert len(checks) == 2, "the two statuses were not read in one turn"
    raw.close(linger=0)
