"""Operator tooling: set-up check, observe-only mode, dry run of a recording, asynchronous execution, e-stop,
a long-lived operator client, the e-stop latch across restarts."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from runbook_walker import free_port

from jepa_robot import protocol as P
from jepa_robot.backends.replay import ReplayBackend
from jepa_robot.backends.sim import SimBackend
from jepa_robot.bridge import BridgeConfig, RobotBridge
from jepa_robot.cli import main as bridge_main
from jepa_robot.episodes import load_episode
from jepa_robot.estop import EStop
from jepa_envs.real_robot.executor import AsyncChunkExecutor
from jepa_envs.real_robot.proxy import BridgeError
from jepa_robot.safety import SafetyConfig
from jepa_robot.operator import OperatorClient, OperatorError

ROOT = Path(__file__).resolve().parents[2]
SETUP = ROOT / "deploy" / "robot" / "arx5_cabinet.toml"


def _setup_file(tmp_path: Path, replace: dict[str, str] | None = None) -> Path:
    """The shipped set-up with its record folder and CurveZMQ keys made under ``tmp_path``."""
    keys = tmp_path / "keys"
    if not (keys / "bridge.key_secret").exists():
        assert bridge_main(["keys", str(keys)]) == 0
    text = SETUP.read_text().replace("/var/lib/jepa-robot/episodes", str(tmp_path / "episodes"))
    text = text.replace("/etc/jepa-robot/keys", str(keys))
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "setup.toml"
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------- check

def test_check_passes_the_shipped_setup(tmp_path, capsys):
    assert bridge_main(["check", str(_setup_file(tmp_path))]) == 0
    out = capsys.readouterr().out
    assert "task Cabinet: 20-D actions" in out and "12 joints" in out and "OK, nothing touched" in out


@pytest.mark.parametrize("old, new, message", [
    ("0.03, 0.03, 0.03, 0.25, 0.25, 0.25, 0.25, 0.25, 0.25, 0.5]", "0.03, 0.03, 0.25, 0.25, 0.25, 0.25, 0.25, 0.25, 0.5]",
     "max_step_delta has 19 entries; this task needs 20"),
    ("joint_low = [-3.0, -0.05, -0.05, -1.6, -1.5, -1.6, ", "joint_low = [-0.05, -0.05, -1.6, -1.5, -1.6, ",
     "joint_low has 11 entries; this task needs 12"),
    ('serial = "000000000003"', 'serial = "000000000002"', "the same serial is listed twice"),
    ("workspace_low = [0.05, -0.35, 0.02]", "workspace_low = [0.05, -0.35]", "workspace bounds are [x, y, z]"),
])
def test_check_names_each_problem_before_any_hardware(tmp_path, capsys, old, new, message):
    assert bridge_main(["check", str(_setup_file(tmp_path, {old: new}))]) == 1
    out = capsys.readouterr().out
    assert message in out and "problem(s); fix them before starting the bridge" in out


def test_check_takes_a_network_operator_socket_only_with_curve(tmp_path, capsys):
    """The shipped set-up has CurveZMQ keys: its operator socket may then listen on the network; without the keys
    the same address is refused (tests/jepa_robot/test_robot_operator_auth.py: for every backend)."""
    network = {'operator_address = "tcp://127.0.0.1:5556"': 'operator_address = "tcp://0.0.0.0:5556"'}
    assert bridge_main(["check", str(_setup_file(tmp_path, network))]) == 0
    assert "OK, nothing touched" in capsys.readouterr().out


def test_check_simulation_safety_table(tmp_path, capsys):
    table = tmp_path / "safety.toml"
    table.write_text("[safety]\njoint_low = [-1.0, -1.0]\njoint_high = [1.0, 1.0]\nmax_step_delta = [5.0, 5.0, 5.0]\n")
    assert bridge_main(["check", str(table), "--task", "PushT"]) == 1
    out = capsys.readouterr().out
    assert "this robot reports no joints" in out and "max_step_delta has 3 entries; this task needs 2" in out
    table.write_text("[safety]\nmax_step_delta = 30.0\n")
    assert bridge_main(["check", str(table), "--task", "PushT"]) == 0


def test_bridge_refuses_a_setup_that_does_not_fit_before_opening_sockets(robot):
    from jepa_robot.backends.sim import SimBackend
    backend = SimBackend("PushT")
    try:
        with pytest.raises(ValueError, match="max_step_delta has 3 entries"):
            RobotBridge(backend, SafetyConfig(max_step_delta=[1.0, 1.0, 1.0]), BridgeConfig())
    finally:
        backend.close()


# ----------------------------------------------------------------------------- observe-only

def test_observe_only_streams_and_refuses_every_motion(robot, tmp_path, capsys):
    bridge = robot.bridge(observe_only=True)
    env = robot.client(bridge)
    assert env.welcome["observe_only"] is True
    frames, info = env.observe(history=2)   # no reset needed
    assert len(frames) == 2 and frames[0]["top_image"].shape == (84, 84, 3) and info["outcome"] is None
    for call in (lambda: env.reset(seed=0), lambda: env.step(np.array([1.0, 2.0])),
                 lambda: env.stream(np.zeros((4, 2)), 0)):
        with pytest.raises(BridgeError, match="observe-only"):
            call()
    with pytest.raises(OperatorError, match="never moves the robot"):
        robot.operator(bridge).home()
    env.close()
    assert bridge_main(["observe", "--address", bridge.control_endpoint, "--seconds", "0.5",
                        "--save", str(tmp_path / "frames")]) == 0
    out = capsys.readouterr().out
    assert "observations in" in out and "top_image: uint8[84, 84, 3]" in out and "agent_pos: float32[2]" in out
    assert (tmp_path / "frames" / "top_image.png").is_file()


# ----------------------------------------------------------------------------- dry run

def test_dry_run_replays_a_recording_through_the_full_bridge(robot, tmp_path):
    """Record an episode on the sim bridge, then serve it with the replay backend: the same actions give the
    recorded frames and outcome with zero action error; a different policy sees its distance to them."""
    bridge = robot.bridge(chunk_budget=3)
    env = robot.client(bridge)
    obs, _ = env.reset(seed=4)
    rng = np.random.default_rng(0)
    chunks = [np.clip(obs["agent_pos"] + rng.normal(0, 20, (8, 2)), 0, 512) for _ in range(3)]
    for chunk in chunks:
        *_, info = env.step_chunk(chunk)
    manifest_path = info["episode_manifest"]
    env.close()
    manifest, arrays = load_episode(manifest_path)

    replay = robot.bridge(backend=ReplayBackend(manifest_path), chunk_budget=3)
    client = robot.client(replay)
    obs, _ = client.reset(seed=0)
    assert np.array_equal(obs["top_image"], arrays["obs/top_image"][0])
    for i, chunk in enumerate(chunks):
        obs, _, terminated, truncated, info = client.step_chunk(chunk)
        assert info["recorded_action_error"] == 0.0
        assert np.array_equal(obs["top_image"], arrays["obs/top_image"][i + 1])
    assert info["outcome"] == manifest["outcome"] and (terminated or truncated)
    obs, _ = client.reset(seed=0)
    *_, info = client.step_chunk(chunks[0] + 3.0)
    assert info["recorded_action_error"] == pytest.approx(3.0)


def test_dry_run_applies_the_setup_limits(tmp_path):
    """With the ARX-5 set-up given, the replay enforces its workspace box (no hardware needed)."""
    from jepa_robot.backends.arx5 import arx5_action_bounds, load_arx5_config
    setup = load_arx5_config(_setup_file(tmp_path))
    low, high = arx5_action_bounds(setup)
    assert low.shape == (20,) and low[0] == 0.05 and high[2] == 0.45 and high[9] == 1.0


# ----------------------------------------------------------------------------- asynchronous execution

def _origin_coded_policy(delay_s: float, horizon: int):
    """Sleeps ``delay_s`` (the inference latency), then plans action i of a chunk from step o as
    (100 + o, 100 + i): every executed action says which chunk and which index it came from."""
    def policy(frames):
        time.sleep(delay_s)
        policy.calls += 1
        return np.stack([[100.0 + policy.origin, 100.0 + i] for i in range(horizon)])
    policy.calls, policy.origin = 0, 0
    return policy


def _run_async(robot, delay_s: float, horizon: int, replan: int, budget: int):
    bridge = robot.bridge(chunk_budget=budget, command_deadline_s=30.0)   # budget x 8 actions at 10 Hz
    env = robot.client(bridge)
    policy = _origin_coded_policy(delay_s, horizon)
    executor = AsyncChunkExecutor(env, policy, history=2, replan_steps=replan)
    original = env.observe

    def observe(history=1):   # let the policy know the origin step it plans from
        frames, info = original(history)
        policy.origin = int(info["step"])
        return frames, info
    env.observe = observe
    record = executor.run_episode(seed=0)
    manifest, arrays = load_episode(bridge.runner.saved_manifests[-1])
    return record, arrays["actions_requested"]


def test_async_executor_runs_each_action_at_the_step_its_chunk_planned(robot):
    """Inference takes 0.25 s (2.5 periods): each chunk arrives ~3 steps late, its first actions are dropped,
    and every executed action is the one its chunk planned for that step; no underflow."""
    record, executed = _run_async(robot, delay_s=0.25, horizon=16, replan=4, budget=3)
    assert record.outcome == "failure" and record.steps == 24 and len(executed) == 24
    origins, index = executed[:, 0] - 100, executed[:, 1] - 100
    assert np.array_equal(origins + index, np.arange(24)), "an action ran at a step its chunk did not plan it for"
    # a chunk streamed after the budget's last action found the episode over (nothing accepted, no lateness)
    late = [d["late_steps"] for d in record.decisions[1:] if d["accepted"]]
    assert min(late) >= 2 and np.median(late) <= 5
    assert all(d["latency_steps"] >= 3 for d in record.decisions)
    assert record.underflow_steps == 0 and record.summary()["late_steps_max"] >= 2


def test_async_executor_reports_queue_underflow(robot):
    """Chunks of 4 actions with 0.6 s inference: the queue runs dry and the robot holds; the bridge counts it."""
    record, executed = _run_async(robot, delay_s=0.6, horizon=4, replan=2, budget=1)
    assert record.underflow_steps > 0 and record.steps == 8
    index = executed[:, 1] - 100
    assert np.all(index < 4)   # never past the end of a chunk: the robot holds instead


# ----------------------------------------------------------------------------- e-stop entry point

def test_operator_commands_start_without_the_heavy_stack(robot):
    bridge = robot.bridge()
    code = ("import sys, time; t = time.perf_counter(); from jepa_robot.operator_cli import main; "
            f"rc = main(['estop', '--operator', {bridge.operator_endpoint!r}]); "
            "heavy = [m for m in ('numpy', 'gymnasium', 'torch', 'pydantic', 'jepa_envs') if m in sys.modules]; "
            "print(rc, heavy, file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stderr.strip().endswith("0 []"), out.stderr
    assert json.loads(out.stdout)["estop"] is True
    assert robot.operator(bridge).status()["estop"] is True


def test_console_script_hands_other_commands_to_the_full_cli(tmp_path):
    out = subprocess.run([sys.executable, "-m", "jepa_robot.operator_cli", "check", str(_setup_file(tmp_path))],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "OK, nothing touched" in out.stdout
    assert P.PROTOCOL_VERSION == 4


# ----------------------------------------------------------------------------- a long-lived operator client

def test_operator_client_stays_usable_after_timeouts():
    """Three calls in a row with no bridge each time out with TimeoutError (the REQ socket used to raise a raw
    ZMQError from the second on); the same client then reaches a bridge started at that address, three calls in
    a row, and none of the timed-out e-stops was delivered to it late."""
    address = f"tcp://127.0.0.1:{free_port()}"
    op = OperatorClient(address, timeout_s=0.3)
    try:
        for call in (op.estop, op.status, op.estop):
            start = time.monotonic()
            with pytest.raises(TimeoutError, match="no robot bridge answered"):
                call()
            assert time.monotonic() - start < 2.0
        bridge = RobotBridge(SimBackend("PushT"), SafetyConfig(command_deadline_s=60.0),
                             BridgeConfig("tcp://127.0.0.1:*", address)).start()
        try:
            op.timeout_ms = 5000
            assert op.status()["estop"] is False, "a timed-out e-stop must never arrive late"
            assert op.estop()["held"] is True
            assert op.clear_estop()["estop"] is False
        finally:
            bridge.close()
    finally:
        op.close()


def test_estop_latch_survives_a_crash_and_a_restart(tmp_path):
    """The state file: a bridge that did not stop cleanly (or left the e-stop latched) restarts latched and stops
    the robot at start; a clean stop with the e-stop clear restarts free; an unreadable file counts as a crash."""
    state = tmp_path / "state.json"
    stops = []
    first = EStop(lambda: stops.append("stop"), str(state))
    assert first.restore() is None and not first.latched and stops == []
    # the process dies here without mark_clean_exit: the next start is latched and stops the robot
    second = EStop(lambda: stops.append("stop"), str(state))
    assert "unclean restart" in second.restore() and second.latched and stops == ["stop"]
    second.mark_clean_exit()
    third = EStop(lambda: stops.append("stop"), str(state))
    assert "latched before the restart" in third.restore() and third.latched, "a clean stop keeps the latch"
    third.clear()
    third.mark_clean_exit()
    assert EStop(lambda: None, str(state)).restore() is None
    state.write_text("{half a fi")
    assert "unclean restart" in EStop(lambda: None, str(state)).restore()
