"""The safety holes a type-confused peer found (issue 29), each reproduced as reported and then closed.

1. one operator message with an array as its version silenced the e-stop for the life of the bridge;
2. a connection without a session ended the controlling client's episode with one message;
3. a held link kept the episode only for the command watchdog, not for link_grace_s;
4. a chunk of any length ran as "1 chunk" (the budget could be bypassed);
5. a reset manifest JSON cannot hold lost the episode's record at its end;
6. smaller holes: check's traceback, a dry run without bounds, seq 2**63-1 in hello, the row of a NaN.
"""
from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from robot_testkit import raw_socket, recv_reply, wait_for

from jepa_robot import protocol as P
from jepa_robot.backends.replay import ReplayBackend
from jepa_robot.cli import main as bridge_main
from jepa_envs.real_robot.proxy import ActionRefused, BridgeError

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def _nd(dtype: str) -> dict:
    """A msgpack ndarray map of ``dtype`` as the wire carries it (what a confused peer sends as 'v')."""
    arr = np.zeros(2, dtype=dtype)
    return {"__nd__": True, "dtype": arr.dtype.str, "shape": [2], "data": arr.tobytes()}


TYPE_CONFUSED = [_nd("<i8"), _nd("|S8"), _nd("<M8[s]"), _nd("<c16"), {"nested": {"map": [1, 2]}}, [2], "2", 2.0,
                 2**64 - 1, -1, b"\x02", True, None]


def _running_client(robot, bridge):
    env = robot.client(bridge)
    obs, _ = env.reset(seed=1)
    assert env.step(obs["agent_pos"])[4]["outcome"] is None
    return env, obs


# ----------------------------------------------------------------------------- 1. the e-stop


@pytest.mark.parametrize("version", TYPE_CONFUSED, ids=repr)
def test_type_confused_operator_message_never_silences_the_estop(robot, ctx, version):
    """``{"v": <array>, "type": "status"}`` used to raise before the REP socket replied: every later operator
    command (estop included) then timed out. Now it is answered, and the e-stop still stops the robot."""
    bridge = robot.bridge()
    env, obs = _running_client(robot, bridge)
    op = raw_socket(ctx, zmq.REQ, bridge.operator_endpoint)
    op.send(msgpack.packb({"v": version, "type": "status"}, use_bin_type=True))
    reply = recv_reply(op)
    assert reply["type"] == P.ERROR and reply["code"] in (P.ERR_VERSION, P.ERR_BAD_MESSAGE)
    assert env.step(obs["agent_pos"])[4]["outcome"] is None, "the client's episode is untouched"
    op = robot.operator(bridge)
    assert op.estop()["estop"] is True
    status = wait_for(lambda: (s := op.status())["episode"]["outcome"] and s)
    assert status["estop"] is True and status["episode"]["reason"] == "estop"
    with pytest.raises(BridgeError, match="emergency stop is latched"):
        env.reset(seed=2)


def test_estop_latches_before_the_event_loop_answers(robot):
    """The e-stop's latch is set and the backend's stop called by the operator thread itself: a loop stuck inside
    a long backend call cannot delay either, and no action is applied after it (the loop checks the latch
    before each one)."""
    bridge = robot.bridge()
    env, obs = _running_client(robot, bridge)
    backend = bridge.backend
    applied_after_latch = []
    original_apply, original_reset = backend.apply, backend.reset

    def slow_reset(seed=None):
        time.sleep(1.5)   # a homing move: the loop is busy inside the backend
        return original_reset(seed)

    stops = []
    backend.emergency_stop = lambda: stops.append(time.monotonic())

    def watched_apply(action):
        if bridge.estop.latched:
            applied_after_latch.append(action)
        return original_apply(action)

    backend.reset, backend.apply = slow_reset, watched_apply
    resetting = threading.Thread(target=env.reset, kwargs={"seed": 3})
    resetting.start()
    time.sleep(0.3)
    start = time.monotonic()
    status = robot.operator(bridge).estop()
    elapsed = time.monotonic() - start
    assert elapsed < 1.0, f"the e-stop waited {elapsed:.2f}s for the busy loop"
    assert status["estop"] is True and status["held"] is True and bridge.estop.latched
    assert len(stops) == 1 and start <= stops[0] <= start + elapsed, "the robot was stopped by the e-stop's path"
    assert resetting.is_alive(), "answered while the loop was still inside the backend's reset"
    resetting.join(timeout=10)
    status = wait_for(lambda: (s := robot.operator(bridge).status())["episode"]["outcome"] and s)
    assert status["estop"] and status["episode"]["reason"] == "estop", "the loop applied the latch once free"
    *_, truncated, info = env.step(obs["agent_pos"])
    assert truncated and info["executed"] == 0 and info["interrupted"] == "estop"
    with pytest.raises(BridgeError, match="emergency stop is latched"):
        env.reset(seed=4)
    assert applied_after_latch == []


# ----------------------------------------------------------------------------- 2. strangers


STRANGER_MESSAGES = [
    {"v": P.PROTOCOL_VERSION, "type": P.STEP, "seq": 99, "session": "sessión-ñ", "action": [1.0, 2.0]},
    {"v": P.PROTOCOL_VERSION, "type": P.RESET, "seq": 99, "session": "日本語"},
    {"v": P.PROTOCOL_VERSION, "type": P.BYE, "seq": 99, "session": _nd("<i8")},
    {"v": P.PROTOCOL_VERSION, "type": P.BYE, "seq": 99, "session": b"\xff\xfe"},
    {"v": _nd("<i8"), "type": P.BYE, "seq": 99},
    {"v": _nd("<c16"), "type": P.STEP, "seq": 99},
    {"v": P.PROTOCOL_VERSION, "type": {"nested": 1}, "seq": 99},
    {"v": P.PROTOCOL_VERSION, "type": P.HELLO, "seq": 1, "task": _nd("|S8")},
    {"v": P.PROTOCOL_VERSION, "type": P.HELLO, "seq": 1, "client": ["x"]},
    {"v": P.PROTOCOL_VERSION, "type": P.RESUME, "seq": 99, "session": 12345, "awaiting": _nd("<i8")},
]


def test_a_message_without_a_valid_session_never_touches_the_controlling_session(robot, ctx):
    """Each of these once ended (or could end) the running episode of the client in control; now each is
    answered with an error naming the problem and the controlling client carries on as if nothing happened."""
    bridge = robot.bridge()
    env, obs = _running_client(robot, bridge)
    stranger = raw_socket(ctx, zmq.DEALER, bridge.control_endpoint)
    for message in STRANGER_MESSAGES:
        stranger.send(msgpack.packb(message, use_bin_type=True))
        reply = recv_reply(stranger)
        assert reply["type"] == P.ERROR
        assert reply["code"] in (P.ERR_NOT_CONTROLLING, P.ERR_BAD_MESSAGE, P.ERR_VERSION, P.ERR_BUSY, P.ERR_TASK)
    status = robot.operator(bridge).status()
    assert status["client"] == env._client and status["link"] == "up"
    assert status["episode"]["outcome"] is None and status["episode"]["steps"] == 1
    assert status["counters"].get("internal_errors", 0) == 0
    assert env.step(obs["agent_pos"])[4]["executed"] == 1


def test_hello_cannot_lock_its_own_session_with_the_last_seq(robot, ctx):
    bridge = robot.bridge()
    dealer = raw_socket(ctx, zmq.DEALER, bridge.control_endpoint)
    dealer.send(P.encode({"type": P.HELLO, "seq": P.MAX_SEQ}))
    reply = recv_reply(dealer)
    assert reply["code"] == P.ERR_BAD_MESSAGE and "leaves no room" in reply["message"]
    assert robot.operator(bridge).status()["client"] is None
    dealer.send(P.encode({"type": P.HELLO, "seq": 1}))
    assert recv_reply(dealer)["type"] == P.WELCOME


# ----------------------------------------------------------------------------- 4. chunk length and budget


def test_chunk_length_is_bounded_by_the_tasks_chunk_size(robot):
    bridge = robot.bridge()
    env, obs = _running_client(robot, bridge)
    spec = env.task_spec
    assert env.welcome["max_chunk_actions"] == spec.n_action_steps == 8
    too_long = np.tile(obs["agent_pos"], (spec.n_action_steps + 1, 1))
    with pytest.raises(ActionRefused, match="at most 8 per chunk"):
        env.step_chunk(too_long)
    with pytest.raises(ActionRefused, match=f"at most {spec.horizon} per chunk"):
        env.stream(np.tile(obs["agent_pos"], (spec.horizon + 1, 1)), 1)
    assert robot.operator(bridge).status()["episode"]["steps"] == 1, "nothing of a refused chunk ran"
    assert env.step_chunk(too_long[:8])[4]["executed"] == 8


def test_the_budget_counts_actions_as_well_as_chunks(robot):
    """Single steps between chunks used to let the chunk count lag the actions; the episode now ends at exactly
    chunk_budget x n_action_steps actions, cutting the chunk that would pass it."""
    bridge = robot.bridge(chunk_budget=2)
    env, obs = _running_client(robot, bridge)        # 1 step
    for _ in range(2):
        env.step(obs["agent_pos"])                    # 3 steps: still inside the first chunk
    info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))[4]
    assert info["executed"] == 8 and info["outcome"] is None       # 11 actions, 2 chunks counted
    *_, terminated, truncated, info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
    assert info["executed"] == 5, "only the actions left in the 16-action budget run"
    assert (terminated or truncated) and info["outcome"] in ("success", "failure")
    assert robot.operator(bridge).status()["episode"]["steps"] == 16


def test_nan_in_a_chunk_is_named_by_row_and_column(robot):
    bridge = robot.bridge()
    env, obs = _running_client(robot, bridge)
    chunk = np.tile(obs["agent_pos"], (8, 1)).astype(np.float64)
    chunk[3, 1] = np.nan
    with pytest.raises(ActionRefused, match="row 3 column 1"):
        env.step_chunk(chunk)


# ----------------------------------------------------------------------------- 5. the episode record


@pytest.mark.parametrize("bad", [b"\x00\x01", np.arange(3.0), {"nested": [b"x"]}, float("nan")],
                         ids=["bytes", "array", "nested-bytes", "nan"])
def test_a_manifest_json_cannot_hold_is_refused_before_anything_moves(robot, bad):
    bridge = robot.bridge(chunk_budget=1)
    env = robot.client(bridge)
    with pytest.raises(BridgeError, match="cannot be stored in the episode's JSON record"):
        env.reset(seed=0, options={"manifest": {"checkpoint": "x.pt", "bad": bad}})
    assert robot.operator(bridge).status()["episode"] is None, "no episode started"
    obs, _ = env.reset(seed=0, options={"manifest": {"checkpoint": "x.pt"}})
    *_, info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
    manifest = json.loads(Path(info["episode_manifest"]).read_text())
    assert manifest["manifest"]["checkpoint"] == "x.pt" and Path(info["episode_manifest"]).with_suffix(".h5").is_file()


def test_a_record_that_cannot_be_written_is_reported_and_the_bridge_goes_on(robot, tmp_path):
    bridge = robot.bridge(chunk_budget=1)
    blocker = tmp_path / "episodes"
    blocker.write_text("a file where the record folder should be")
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    *_, terminated, truncated, info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
    assert terminated or truncated
    events = robot.operator(bridge).status()["events"]
    assert any(e["kind"] == "record_failed" for e in events)
    assert not list(tmp_path.rglob("*.tmp")), "nothing half-written"
    obs, _ = env.reset(seed=1)   # still serving
    assert env.step(obs["agent_pos"])[4]["executed"] == 1


# ----------------------------------------------------------------------------- 6. operator tools


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jepa_robot.cli", *args], capture_output=True, text=True,
                          timeout=120)


def test_check_names_an_unknown_task_without_a_traceback(tmp_path):
    table = tmp_path / "safety.toml"
    table.write_text("[safety]\n")
    out = _cli("check", str(table), "--task", "Nope")
    assert out.returncode != 0 and "Traceback" not in out.stderr + out.stdout
    assert "unknown task 'Nope'" in out.stderr + out.stdout and "known tasks" in out.stderr + out.stdout
    setup = tmp_path / "setup.toml"
    setup.write_text((Path(__file__).resolve().parents[2] / "deploy/robot/arx5_cabinet.toml").read_text()
                     .replace('task = "Cabinet"', 'task = "Cabnet"'))
    out = _cli("check", str(setup))
    assert out.returncode == 1 and "Traceback" not in out.stderr + out.stdout and "unknown task 'Cabnet'" in out.stdout


def test_check_refuses_a_watchdog_that_would_fire_before_a_lost_link_is_seen(tmp_path, capsys):
    table = tmp_path / "safety.toml"
    table.write_text("[safety]\ncommand_deadline_s = 0.05\n")   # PushT at 10 Hz: link timeout 0.1 s
    assert bridge_main(["check", str(table), "--task", "PushT"]) == 1
    assert "must be below command_deadline_s" in capsys.readouterr().out


def test_a_network_bind_without_curve_needs_an_explicit_flag(robot, tmp_path, capsys):
    setup = tmp_path / "setup.toml"
    text = (Path(__file__).resolve().parents[2] / "deploy/robot/arx5_cabinet.toml").read_text()
    text = "\n".join(line for line in text.splitlines() if not line.startswith("curve_"))
    setup.write_text(text.replace("/var/lib/jepa-robot/episodes", str(tmp_path / "episodes")))
    assert bridge_main(["check", str(setup)]) == 1
    assert "reachable from the network without encryption" in capsys.readouterr().out
    assert bridge_main(["check", str(setup), "--insecure-network"]) == 0
    assert "WARNING control_address" in capsys.readouterr().out
    from jepa_robot.backends.sim import SimBackend
    from jepa_robot.bridge import BridgeConfig, RobotBridge
    backend = SimBackend("PushT")
    try:
        with pytest.raises(ValueError, match="--insecure-network"):
            RobotBridge(backend, config=BridgeConfig("tcp://0.0.0.0:*", "tcp://127.0.0.1:*"))
    finally:
        backend.close()
    out = _cli("serve", "--backend", "sim", "--task", "PushT", "--bind", "tcp://0.0.0.0:5999")
    assert out.returncode != 0 and "Traceback" not in out.stderr and "--insecure-network" in out.stderr


def test_dry_run_never_runs_without_bounds(robot, tmp_path):
    """A recording now carries the bounds it ran under, so a dry run without --config refuses what the robot
    would have refused (9999 used to execute); a recording without them needs --config."""
    bridge = robot.bridge(chunk_budget=1)
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    *_, info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
    manifest_path = Path(info["episode_manifest"])
    env.close()
    replay = robot.bridge(backend=ReplayBackend(manifest_path), chunk_budget=1)
    client = robot.client(replay)
    client.reset(seed=0)
    *_, info = client.step(np.array([9999.0, 9999.0]))
    assert info["executed"] == 0 and info["safety"][0]["refused"]
    client.close()
    old = json.loads(manifest_path.read_text())
    del old["manifest"]["action_low"], old["manifest"]["action_high"]
    old_path = manifest_path.with_name("old.json")
    old_path.write_text(json.dumps(old))
    with pytest.raises(ValueError, match="pass --config SETUP.toml"):
        ReplayBackend(old_path)


def test_estop_press_and_clear_are_atomic():
    """The latch and its facts (``latched_at``, ``reason``) change together under the lock (issue 35, F10: the
    press used to set the latch before taking the lock, and 8 of 20,000 press/clear races ended unlatched with
    ``latched_at`` set). Deterministic part: while the lock is held, a press does not set the latch either.
    Then press/clear races with a tiny switch interval: the state is consistent after every one."""
    from jepa_robot.estop import EStop
    stops = []
    estop = EStop(lambda: stops.append(1))
    with estop._cv:
        presser = threading.Thread(target=estop.press)
        presser.start()
        presser.join(timeout=0.2)
        assert presser.is_alive() and not estop.latched and estop.latched_at is None
    presser.join(timeout=5)
    assert estop.latched and estop.latched_at is not None and stops == [1]
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        inconsistent = 0
        for _ in range(1500):
            e = EStop(lambda: None)
            go = threading.Barrier(2)
            threads = [threading.Thread(target=lambda: (go.wait(), e.press())),
                       threading.Thread(target=lambda: (go.wait(), e.clear()))]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            inconsistent += (e.latched_at is not None) != e.latched or (e.reason is not None) != e.latched
    finally:
        sys.setswitchinterval(interval)
    assert inconsistent == 0
