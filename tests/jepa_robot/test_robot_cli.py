"""The console script (serve as default subcommand, operator commands, bench) and the gym registration."""
from __future__ import annotations

import json
import subprocess
import sys

import gymnasium as gym
import numpy as np

from jepa_robot.cli import main
from jepa_envs.tasks.spec import get_task_spec


def test_real_task_specs_registered():
    expected = {"Cabinet": 20, "CupStack": 10, "CupUpright": 10, "PlateGrape": 20, "PenInsert": 10}
    for name, dim in expected.items():
        spec = get_task_spec(f"JEPA/RealRobot-{name}-v0")
        assert spec.suite == "real" and spec.action_dim == dim and spec.num_arms == dim // 10
        assert spec.cameras == ("base", "left_wrist", "right_wrist") and spec.image_size == 128
        assert spec.control_hz == 10.0 and spec.extra["driver_hz"] == 30.0 and spec.n_action_steps == 8
        assert spec.extra["chunk_budget"] > 0 and spec.env_id in gym.registry
    assert "JEPA/RealRobot-v0" in gym.registry


def test_registration_imports_no_zmq_or_sdk():
    code = "import sys, jepa_envs, gymnasium as gym; assert 'JEPA/RealRobot-v0' in gym.registry; " \
           "print(sorted(m for m in ('zmq', 'msgpack', 'arx5_interface', 'pyrealsense2') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]"


def test_serve_is_default_and_operator_commands(capsys):
    server = subprocess.Popen(
        [sys.executable, "-m", "jepa_robot.cli", "--backend", "sim", "--task", "PushT",
         "--bind", "tcp://127.0.0.1:*", "--operator-bind", "tcp://127.0.0.1:*"],
        stdout=subprocess.PIPE, text=True)
    try:
        banner = server.stdout.readline()
        assert "serving PushT (SimBackend)" in banner, banner
        operator = banner.rsplit("operator socket ", 1)[1].strip()
        assert main(["status", "--operator", operator]) == 0
        assert json.loads(capsys.readouterr().out)["task"] == "PushT"
        assert main(["estop", "--operator", operator]) == 0
        assert json.loads(capsys.readouterr().out)["estop"] is True
        assert main(["clear-estop", "--operator", operator]) == 0
        assert json.loads(capsys.readouterr().out)["estop"] is False
        assert main(["confirm", "success", "--operator", operator]) == 1
        assert "no episode is running" in capsys.readouterr().err
        assert main(["shutdown", "--operator", operator]) == 0
        assert server.wait(timeout=30) == 0
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()


def test_serve_argument_errors(capsys):
    """A refused set-up exits 2 (the supervisor does not restart it) with one line naming the fix."""
    assert main(["--backend", "sim"]) == 2
    assert "needs --task" in capsys.readouterr().err
    assert main(["serve", "--backend", "arx5"]) == 2
    assert "needs --config" in capsys.readouterr().err


def test_bench_prints_numbers(capsys, tmp_path):
    out_json = tmp_path / "bench.json"
    assert main(["bench", "--steps", "20", "--chunks", "4", "--estop-runs", "2", "--out", str(out_json)]) == 0
    captured = capsys.readouterr()
    text = captured.out
    assert "3 camera(s) of 128x128" in text and "overhead per chunk" in text and "operator entry point" in text
    # its bar on stderr: 2 x (20 steps + 4 chunks) + 2 e-stop runs, all done
    assert "robot bench: 100%" in captured.err and "50/50" in captured.err
    result = json.loads(out_json.read_text())
    assert result["obs_payload_bytes"] == 3 * 128 * 128 * 3 + 2 * 4
    for where in ("in_process", "bridge"):
        assert result[where]["step"]["n"] == 20 and result[where]["chunk"]["n"] == 4
        assert 0 < result[where]["step"]["p50_ms"] <= result[where]["step"]["p99_ms"]
    # 20 steps make 3 decision chunks, then 4 chunks in a new episode; each episode's first is left out
    assert result["bridge_frame_to_chunk"]["count"] == (3 - 1) + (4 - 1)
    estop = result["estop_command"]
    # numbers, not a race: which entry point is faster is the benchmark's to print (2 runs under load flip it)
    assert estop["runs"] == 2 and estop["operator_cli"]["p50_ms"] > 0 and estop["full_cli"]["p50_ms"] > 0


def test_serve_prompt_confirms_through_operator_api(robot, monkeypatch):
    """The stdin prompt of `serve` answers a budget-spent episode through the bridge's command queue."""
    from jepa_robot.cli import _prompt_operator

    answers = iter(["maybe", "y"])   # an unclear answer is asked again
    monkeypatch.setattr("builtins.input", lambda prompt: next(answers))
    bridge = robot.bridge(chunk_budget=1, success_source="operator")
    bridge.on_confirmation_needed = _prompt_operator(bridge)
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    _, _, terminated, truncated, info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
    assert terminated and not truncated and info["is_success"] and info["outcome"] == "success"
