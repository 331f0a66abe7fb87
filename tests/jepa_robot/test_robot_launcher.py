"""Task launcher: a trained policy checkpoint driven through the bridge by `jepa-policy robot`."""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from jepa_policy.cli import main
from jepa_robot.episodes import load_episode
from jepa_policy.robot import run_episodes


class ReplayPolicy:
    """A scripted policy: holds the agent where it is, with the act/reset interface of jepa_policy."""

    def __init__(self):
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def act(self, obs):
        return obs["agent_pos"]


def test_run_episodes_counts_success_and_tags_manifests(robot):
    bridge = robot.bridge(chunk_budget=2)
    env = robot.client(bridge)
    policy = ReplayPolicy()
    seen = []
    summary = run_episodes(env, policy, episodes=2, seed=5, manifest={"checkpoint": "scripted"},
                           before_episode=seen.append)
    assert seen == [0, 1] and policy.resets == 3 + 2   # three around the warm-up, then one per episode
    assert [e["steps"] for e in summary["episodes"]] == [16, 16]   # 2 chunks of 8 actions each
    assert summary["success_rate"] == 0.0 and summary["successes"] == 0
    manifest, _ = load_episode(summary["episodes"][1]["episode_manifest"])
    assert manifest["manifest"]["checkpoint"] == "scripted" and manifest["manifest"]["episode_index"] == 1
    assert manifest["manifest"]["seed"] == 6
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        run_episodes(env, policy, episodes=0)


def test_cli_run_with_a_trained_checkpoint(robot, pusht_demo_file, tmp_path, capsys):
    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.train import load_config, train

    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path / "train"), steps=2, warmup_steps=0, batch_size=4,
                      model={"width": 32, "layers": 1, "heads": 2})
    checkpoint = train(cfg, demos)["checkpoint"]
    wrong_size = robot.bridge(chunk_budget=1)
    with pytest.raises(SystemExit, match="--image-size 32"):
        main(["robot", "--address", wrong_size.control_endpoint, "--checkpoint", str(checkpoint), "--no-wait"])
    bridge = robot.bridge(chunk_budget=2, image_size=32)
    out_json = tmp_path / "summary.json"
    assert main(["robot", "--address", bridge.control_endpoint, "--checkpoint", str(checkpoint), "--episodes", "1",
                 "--no-wait", "--out", str(out_json)]) == 0
    summary = json.loads(out_json.read_text())
    assert summary["episodes"][0]["steps"] == 16 and summary["episodes"][0]["chunks"] == 2
    manifest, arrays = load_episode(summary["episodes"][0]["episode_manifest"])
    assert manifest["manifest"]["checkpoint"] == str(Path(checkpoint).resolve())
    assert manifest["manifest"]["method"] == "JEPA Policy" and arrays["obs/top_image"].shape[1:] == (32, 32, 3)
    with pytest.raises(SystemExit, match="not found"):
        main(["robot", "--checkpoint", str(tmp_path / "missing.pt")])


class SlowFirstCall(ReplayPolicy):
    """A policy whose first call pays a one-off cost longer than the bridge's watchdog allows."""

    def __init__(self, first_call_s: float):
        super().__init__()
        self.first_call_s, self.calls = first_call_s, 0

    def act(self, obs):
        self.calls += 1
        if self.calls == 1:
            time.sleep(self.first_call_s)
        return super().act(obs)


def test_warm_up_keeps_the_first_call_out_of_the_episode(robot):
    """The first policy call (kernels, caches) takes longer than the watchdog: warmed up before the episode
    it costs nothing there; without the warm-up the watchdog ends the episode on its first decision."""
    bridge = robot.bridge(chunk_budget=1, command_deadline_s=0.5, link_timeout_s=0.4)
    env = robot.client(bridge)
    cold = run_episodes(env, SlowFirstCall(0.9), episodes=1, warmup=False)
    assert cold["episodes"][0]["interrupted"] == "watchdog"
    warm = run_episodes(env, SlowFirstCall(0.9), episodes=1)
    assert warm["warmup_s"] >= 0.9 and warm["episodes"][0]["interrupted"] == ""
    assert warm["episodes"][0]["steps"] == 8 and warm["episodes"][0]["outcome"] == "failure"
