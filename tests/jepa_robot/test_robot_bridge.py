"""The bridge and proxy against the simulated robot: conventions, equivalence with in-process, every safety rule."""
from __future__ import annotations

import importlib.util
import os
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import zmq
from gymnasium.utils.env_checker import check_env

from jepa_robot import protocol as P
from jepa_robot.episodes import load_episode
from jepa_envs.tasks.pusht_expert import PushTExpert, collect_episode
from jepa_envs.real_robot.proxy import ActionRefused, BridgeBusy, BridgeError


def test_proxy_conventions_and_check_env(robot):
    bridge = robot.bridge()
    env = robot.client(bridge, task="PushT")
    spec = env.task_spec
    assert spec.name == "PushT" and env.chunk_budget == 38
    direct = gym.make("JEPA/PushT-v0")
    try:
        assert env.observation_space == direct.observation_space
        assert env.action_space == direct.action_space
    finally:
        direct.close()
    obs, info = env.reset(seed=1)
    assert obs["top_image"].dtype == np.uint8 and obs["top_image"].shape == (84, 84, 3)
    assert obs["agent_pos"].dtype == np.float32 and "is_success" in info
    check_env(env, skip_render_check=True)


def test_seeded_expert_episode_same_through_bridge(robot):
    """The scripted PushT expert's seeded episode, replayed through the bridge, reaches the same states and
    the same success as run in-process (first 16 actions by step, the rest as chunks of 8)."""
    direct = gym.make("JEPA/PushT-v0")
    try:
        ref = collect_episode(direct, seed=0, expert=PushTExpert(seed=0))
        direct.reset(seed=0)
        for action in ref["actions"]:   # replaying the expert's actions in-process gives the final frame
            final_direct = direct.step(action)[0]
    finally:
        direct.close()
    actions = ref["actions"]
    assert ref["success"] and len(actions) > 24
    bridge = robot.bridge()
    env = robot.client(bridge, task="PushT")
    obs, _ = env.reset(seed=0)
    assert np.array_equal(obs["top_image"], ref["obs"]["top_image"][0])
    rewards = []
    for t in range(16):
        obs, reward, terminated, truncated, info = env.step(actions[t])
        rewards.append(reward)
        assert np.array_equal(obs["agent_pos"], ref["obs"]["agent_pos"][t + 1])
        assert np.array_equal(obs["top_image"], ref["obs"]["top_image"][t + 1])
    for c in range(16, len(actions), 8):
        obs, reward, terminated, truncated, info = env.step_chunk(actions[c:c + 8])
        rewards.append(reward)
        if terminated or truncated:
            break
    assert terminated and not truncated and info["is_success"] and info["outcome"] == "success"
    assert np.array_equal(obs["top_image"], final_direct["top_image"])
    assert np.array_equal(obs["agent_pos"], final_direct["agent_pos"])
    assert sum(rewards) == pytest.approx(float(ref["rewards"].sum()), rel=1e-6)
    manifest, arrays = load_episode(info["episode_manifest"])
    assert manifest["is_success"] and manifest["steps"] == len(actions)
    np.testing.assert_array_equal(arrays["actions_executed"], actions.astype(np.float64))


def test_out_of_bounds_refused_and_reported(robot):
    bridge = robot.bridge(action_low=[100.0, 100.0], action_high=[400.0, 400.0])
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    assert np.array_equal(env.action_space.low, [100.0, 100.0])
    before = obs["agent_pos"].copy()
    obs, _, terminated, truncated, info = env.step(np.array([450.0, 200.0]))
    assert np.array_equal(obs["agent_pos"], before), "a refused action must not move the robot"
    assert info["executed"] == 0 and info["safety"][0]["refused"]
    assert "indices [0]" in info["safety"][0]["violations"][0]
    assert not (terminated or truncated)
    obs, _, _, _, info = env.step(np.array([300.0, 200.0]))
    assert info["executed"] == 1 and info["safety"] == []
    assert not np.array_equal(obs["agent_pos"], before)


def test_out_of_bounds_clipped_when_configured(robot):
    bridge = robot.bridge(action_low=[100.0, 100.0], action_high=[400.0, 400.0], on_violation="clip")
    env = robot.client(bridge)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([450.0, 50.0]))
    assert info["executed"] == 1 and info["safety"][0]["clipped"] and not info["safety"][0]["refused"]
    env.reset(seed=1)   # ends and records the first episode
    manifest, arrays = load_episode(bridge.runner.saved_manifests[-1])
    assert np.array_equal(arrays["actions_requested"][-1], [450.0, 50.0])
    assert np.array_equal(arrays["actions_executed"][-1], [400.0, 100.0])
    assert manifest["outcome"] == "interrupted" and manifest["safety_events"][0]["kind"] == "clipped"


def test_jump_limit_stops_chunk_at_violation(robot):
    bridge = robot.bridge(max_step_delta=20.0)
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    start = obs["agent_pos"].astype(np.float64)
    chunk = np.stack([start + [5.0 * (i + 1), 0.0] for i in range(8)])
    chunk[3] += [60.0, 0.0]   # a jump of 65 > 20 at index 3
    obs, _, _, _, info = env.step_chunk(chunk)
    assert info["executed"] == 3
    assert info["safety"][0]["index"] == 3 and info["safety"][0]["refused"]
    assert "jump" in info["safety"][0]["violations"][0]


def test_nan_and_wrong_shape_refused(robot):
    bridge = robot.bridge()
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    with pytest.raises(ActionRefused, match="NaN"):
        env.step(np.array([np.nan, 100.0]))
    with pytest.raises(ActionRefused, match=r"shape \(3,\)"):
        env.step(np.array([1.0, 2.0, 3.0]))
    with pytest.raises(ActionRefused, match="NaN"):
        env.step_chunk(np.array([[200.0, 200.0], [np.inf, 1.0]]))
    status = robot.operator(bridge).status()
    assert status["episode"]["steps"] == 0, "nothing of a chunk with a bad action may run"
    assert [e["kind"] for e in status["events"]] == ["invalid_action"] * 3
    obs2, _, _, _, info = env.step(obs["agent_pos"])
    assert info["executed"] == 1


def test_watchdog_holds_and_interrupts(robot):
    bridge = robot.bridge(command_deadline_s=0.3, link_timeout_s=0.25)
    env = robot.client(bridge)
    env.reset(seed=0)
    env.step(np.array([200.0, 200.0]))
    time.sleep(0.8)
    status = robot.operator(bridge).status()
    assert status["episode"]["outcome"] == "interrupted" and status["episode"]["reason"] == "watchdog"
    obs, reward, terminated, truncated, info = env.step(np.array([210.0, 200.0]))
    assert truncated and not terminated and info["interrupted"] == "watchdog" and info["executed"] == 0
    assert not info["is_success"]
    env.reset(seed=1)   # a new episode after the interruption is fine
    assert env.step(np.array([200.0, 200.0]))[4]["executed"] == 1


def test_second_client_refused_until_first_leaves(robot):
    bridge = robot.bridge()
    first = robot.client(bridge, client_name="policy-A")
    with pytest.raises(BridgeBusy, match="already controlled by client 'policy-A'"):
        robot.client(bridge, client_name="policy-B")
    first.close()
    second = robot.client(bridge, client_name="policy-B")
    assert second.reset(seed=0)[0]["top_image"].shape == (84, 84, 3)


def test_estop_mid_chunk_then_explicit_clear(robot):
    bridge = robot.bridge(realtime=True)
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    op = robot.operator(bridge)
    chunk = np.stack([obs["agent_pos"] + [4.0 * i, 0.0] for i in range(1, 9)])
    timer = threading.Timer(0.3, op.estop)   # mid-chunk: the chunk takes 0.8 s at 10 Hz
    timer.start()
    t0 = time.monotonic()
    _, _, terminated, truncated, info = env.step_chunk(chunk)
    elapsed = time.monotonic() - t0
    timer.join()
    assert 1 <= info["executed"] < 8 and elapsed < 0.7
    assert truncated and not terminated and info["interrupted"] == "estop" and info["estop"]
    with pytest.raises(BridgeError, match="emergency stop is latched"):
        env.reset(seed=0)
    op.clear_estop()
    env.reset(seed=0)
    assert env.step(obs["agent_pos"])[4]["executed"] == 1


def test_operator_confirmation_and_episode_record(robot, tmp_path):
    bridge = robot.bridge(chunk_budget=2, success_source="operator")
    env = robot.client(bridge, manifest={"checkpoint": "jepa-policy-100k.pt", "policy": "JEPA Policy"})
    obs, _ = env.reset(seed=3)
    chunk = np.tile(obs["agent_pos"], (8, 1))
    _, _, terminated, truncated, info = env.step_chunk(chunk)
    assert not (terminated or truncated) and not info["is_success"]
    op = robot.operator(bridge)
    timer = threading.Timer(0.3, op.confirm, args=(True,))
    timer.start()
    t0 = time.monotonic()
    _, _, terminated, truncated, info = env.step_chunk(chunk)   # budget spent: waits for the operator
    timer.join()
    assert time.monotonic() - t0 >= 0.25
    assert terminated and not truncated and info["is_success"] and info["outcome"] == "success"
    manifest, arrays = load_episode(info["episode_manifest"])
    assert manifest["manifest"]["checkpoint"] == "jepa-policy-100k.pt" and manifest["manifest"]["seed"] == 3
    assert manifest["outcome"] == "success" and manifest["chunks"] == 2 and manifest["chunk_budget"] == 2
    assert arrays["obs/top_image"].shape == (3, 84, 84, 3)   # reset + after each chunk
    assert arrays["actions_executed"].shape == (16, 2) and arrays["chunk_latency_s"].shape == (2,)
    assert manifest["frame_to_chunk_latency"]["count"] == 1   # first chunk excluded (Sec. 4.8)


def test_operator_declares_failure_early(robot):
    bridge = robot.bridge(success_source="operator")
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    robot.operator(bridge).confirm(False)
    _, _, terminated, truncated, info = env.step(obs["agent_pos"])
    assert truncated and not terminated and not info["is_success"] and info["outcome"] == "failure"


def test_homing_is_explicit_and_interrupts(robot):
    bridge = robot.bridge()
    env = robot.client(bridge)
    env.reset(seed=0)
    status = robot.operator(bridge).home()
    assert status["episode"]["outcome"] == "interrupted" and status["episode"]["reason"] == "homed by the operator"


def test_version_and_task_mismatch(robot):
    bridge = robot.bridge()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, 10000)
    sock.connect(bridge.control_endpoint)
    try:
        sock.send(P.encode({"type": P.HELLO, "v": 99}))
        reply = P.decode(sock.recv())
    finally:
        sock.close(linger=0)
        ctx.term()
    assert reply["code"] == P.ERR_VERSION and "v99" in reply["message"]
    with pytest.raises(BridgeError, match="serves task 'PushT'.*'Cabinet'"):
        robot.client(bridge, task="Cabinet")
    with pytest.raises(BridgeError, match="serves task 'PushT'"):
        gym.make("JEPA/RealRobot-Cabinet-v0", address=bridge.control_endpoint, timeout_s=10.0)


def test_render_images_switch(robot):
    bridge = robot.bridge()
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    assert obs["top_image"].any()
    env.set_render_images(False)
    obs, *_ = env.step(obs["agent_pos"])
    assert not obs["top_image"].any()
    env.set_render_images(True)
    obs, *_ = env.step(obs["agent_pos"])
    assert obs["top_image"].any()


def test_no_bridge_times_out_with_hint():
    from jepa_envs.real_robot.proxy import RealRobotEnv
    with pytest.raises(TimeoutError, match="jepa-robot-bridge serve"):
        RealRobotEnv(address="tcp://127.0.0.1:9", timeout_s=0.3)


@pytest.mark.robosuite
@pytest.mark.skipif(importlib.util.find_spec("robosuite") is None, reason="robosuite is not installed")
def test_robosuite_task_through_bridge_checks_rotations_and_joints(robot, monkeypatch):
    """Square through the bridge: degenerate rotations refused; measured joints outside the configured
    limits (Panda joint 3 rests near -2.62 rad, the limit here is -2.5) hold the robot and end the episode."""
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "osmesa"))
    bridge = robot.bridge(task="Square", joint_low=[-3.0, -2.0, -3.0, -2.5, -3.0, -1.0, -3.0],
                          joint_high=[3.0, 2.0, 3.0, 0.0, 3.0, 4.0, 3.0], max_step_delta=0.05)
    env = robot.client(bridge, task="Square")
    assert env.action_space.shape == (10,) and env.task_spec.cameras == ("agentview", "robot0_eye_in_hand")
    obs, _ = env.reset(seed=0)
    assert obs["agentview_image"].shape == (84, 84, 3) and obs["robot0_eef_quat"].dtype == np.float32
    hold = bridge.backend.current_action()
    assert hold.shape == (10,)
    far = hold.copy()
    far[0] += 0.2
    _, _, _, _, info = env.step(far)   # jump reference after reset is the measured pose
    assert info["executed"] == 0 and "jump" in info["safety"][0]["violations"][0]
    degenerate = hold.copy()
    degenerate[6:9] = degenerate[3:6]   # both 6-D rotation columns parallel
    with pytest.raises(ActionRefused, match="degenerate"):
        env.step(degenerate)
    _, _, terminated, truncated, info = env.step(hold)
    assert info["executed"] == 1 and info["safety"] == []
    assert truncated and not terminated and info["interrupted"] == "joint_limit"
    status = robot.operator(bridge).status()
    assert "joints [3]" in [e for e in status["events"] if e["kind"] == "joint_limit"][0]["message"]


def test_three_camera_payload_at_128_passes_check_env(robot):
    """The bench configuration: each PushT frame served as three 128x128 streams, labelled replicas."""
    bridge = robot.bridge(image_size=128, camera_replicas=3)
    env = robot.client(bridge)
    assert env.task_spec.image_keys == ("top_image", "top_replica1_image", "top_replica2_image")
    obs, _ = env.reset(seed=2)
    assert all(obs[k].shape == (128, 128, 3) for k in env.task_spec.image_keys)
    assert np.array_equal(obs["top_image"], obs["top_replica2_image"])
    check_env(env, skip_render_check=True)


def test_estop_while_waiting_for_confirmation_ends_the_episode(robot):
    bridge = robot.bridge(chunk_budget=1, success_source="operator")
    env = robot.client(bridge)
    obs, _ = env.reset(seed=0)
    op = robot.operator(bridge)
    timer = threading.Timer(0.3, op.estop)
    timer.start()
    _, _, terminated, truncated, info = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
    timer.join()
    assert truncated and not terminated and not info["is_success"] and info["interrupted"] == "estop"
