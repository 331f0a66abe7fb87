"""deploy/robot/RUNBOOK.md is walked as written, in its rehearsal set-up (the simulated backend, on free ports):
keys, check, observe-only, start under the supervisor, e-stop, confirmation, a crash and the latched restart,
status and stop. Between the blocks the test plays the
policy computer (a real client over the control socket)."""
from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from runbook_walker import Shell, free_port, runbook_blocks

from jepa_envs.real_robot.proxy import RealRobotEnv
from jepa_policy.train import load_config

ROOT = Path(__file__).resolve().parents[2]
RUNBOOK = ROOT / "deploy" / "robot" / "RUNBOOK.md"


@pytest.mark.timeout(300)
def test_robot_runbook_walks_in_rehearsal(tmp_path):
    blocks = [body for info, body in runbook_blocks(RUNBOOK.read_text()) if info == "sh"]
    assert len(blocks) == 10, "the walk below follows the robot RUNBOOK's sh blocks one by one"
    real, rehearsal, keys, check, observe_only, start, estop, confirm, crash, stop = blocks
    assert "--backend arx5" in real and "--backend sim" in rehearsal
    control, operator = free_port(), free_port()
    shell = Shell(tmp_path, {"5555": str(control), "5556": str(operator)})
    address = f"tcp://127.0.0.1:{control}"
    shell.run(real)   # the real robot's variables: exporting them touches nothing
    shell.run(rehearsal)
    try:
        out = shell.run(keys)
        assert "bridge.key_secret" in out and "policy-pc.key" in out
        assert sorted(p.name for p in (tmp_path / "rehearsal-keys").rglob("*_secret")) == ["bridge.key_secret"]
        assert "OK, nothing touched" in shell.run(check)
        shell.run(observe_only)
        assert sorted(p.name for p in (tmp_path / "observed-frames").iterdir()) == ["top_image.png"]
        assert shell.run(start).split()[:2] == ["PushT", "False"]
        # the policy computer runs an episode; the operator's e-stop interrupts it
        env = RealRobotEnv(address=address, client_name="policy-pc", timeout_s=30.0)
        # the rehearsal serves what the README's cpu-preset checkpoint acts on (jepa-policy robot refuses another)
        assert env.task_spec.image_size == load_config("PushT", "cpu").image_size == 48
        obs, _ = env.reset(seed=0)
        assert obs["top_image"].shape == (48, 48, 3)
        env.step(obs["agent_pos"])
        assert "estop" in shell.run(estop).splitlines(), "the status names the e-stop as the reason"
        # a new episode runs to its budget (2 chunks) and waits for the operator's confirmation
        obs, _ = env.reset(seed=1)
        env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
        result = {}
        last = threading.Thread(target=lambda: result.update(
            reply=env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))))
        last.start()
        deadline = time.monotonic() + 30   # the chunk runs at 10 Hz, then the bridge asks for confirmation
        while not json.loads(shell.run("jepa-robot-bridge status"))["awaiting_confirmation"]:
            assert time.monotonic() < deadline, (tmp_path / "bridge.log").read_text()
            time.sleep(0.1)
        shell.run(confirm)
        last.join(timeout=30)
        _, _, terminated, _, info = result["reply"]
        assert terminated and info["outcome"] == "success"
        env.close()
        # a crash: the supervisor restarts the bridge, latched until the operator clears it
        out = shell.run(crash)
        assert "unclean restart" in out, out
        assert "SIGABRT" in (tmp_path / "bridge.log").read_text(), "the supervisor says how the bridge ended"
        shell.run(stop)
        status = json.loads((tmp_path / "bridge-status.json").read_text())
        assert [e["kind"] for e in status["events"]].count("estop") == 1
        manifests = sorted((tmp_path / "rehearsal-episodes" / "PushT").glob("*.json"))
        outcomes = sorted(json.loads(m.read_text())["outcome"] for m in manifests)
        assert outcomes == ["interrupted", "success"]
    finally:
        shell.run("jepa-robot-bridge shutdown --timeout 2 || true")


def test_robot_runbook_console_blocks_name_real_files():
    text = RUNBOOK.read_text()
    console = "\n".join(body for info, body in runbook_blocks(text) if info == "console")
    for path in re.findall(r"deploy/robot/[\w./-]+", console):
        assert (ROOT / path).is_file(), path
    unit = (ROOT / "deploy/robot/jepa-robot-bridge.service").read_text()
    assert ("ExecStart=/opt/jepa-policy/.venv/bin/jepa-robot-bridge supervise --state-file "
            "/var/lib/jepa-robot/bridge-state.json --backend arx5 --config /etc/jepa-robot/arx5.toml") in unit
    assert "jepa-robot-bridge.service" in console
