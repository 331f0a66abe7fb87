"""The PushT imitation-ceiling probe: true-state features, windows, fitting, rollouts, CLI and error paths."""
import json

import h5py
import numpy as np
import pytest
import torch

from jepa_policy.demo.ceiling import evaluate_state_policy, read_state_demos, state_features, train_state_policy
from jepa_policy.demo.cli import main

pytestmark = pytest.mark.usefixtures("one_thread")


def test_state_features_encode_the_angle_without_wrap_around():
    s = np.array([[1.0, 2.0, 3.0, 4.0, np.pi / 2], [1.0, 2.0, 3.0, 4.0, np.pi / 2 + 2 * np.pi]])
    f = state_features(s)
    assert f.shape == (2, 6) and np.allclose(f[0], [1, 2, 3, 4, 0, 1], atol=1e-12)
    assert np.allclose(f[0], f[1])                          # a full turn is the same pose
    with pytest.raises(ValueError, match="agent x, y, block x, y, angle"):
        state_features(np.zeros((3, 4)))


def test_read_state_demos_matches_the_file_and_rejects_other_tasks(pusht_demo_file, tmp_path):
    states, actions, ends, env_args = read_state_demos(pusht_demo_file)
    with h5py.File(pusht_demo_file, "r") as f:
        lengths = [len(f["data"][f"demo_{i}"]["actions"]) for i in range(4)]
        assert np.array_equal(states[:lengths[0]], f["data"]["demo_0"]["states"][:])
    assert ends.tolist() == np.cumsum(lengths).tolist() and states.shape == (sum(lengths), 5)
    assert actions.shape == (sum(lengths), 2) and env_args["env_name"] == "PushT"
    other = tmp_path / "other.hdf5"
    other.write_bytes(pusht_demo_file.read_bytes())
    with h5py.File(other, "r+") as f:
        f["data"].attrs["env_args"] = json.dumps({**env_args, "env_name": "ToolHang"})
    with pytest.raises(ValueError, match="defined for the embedded PushT task"):
        read_state_demos(other)
    with pytest.raises(FileNotFoundError, match="make-demos"):
        read_state_demos(tmp_path / "missing.hdf5")


def test_state_policy_fits_its_demonstrations_and_acts_in_env_units(pusht_demo_file):
    states, actions, ends, _ = read_state_demos(pusht_demo_file)
    short, fit_short = train_state_policy(pusht_demo_file, steps=5, batch_size=32, warmup=1, seed=0)
    policy, fit = train_state_policy(pusht_demo_file, steps=300, batch_size=32, warmup=20, seed=0)
    assert fit["windows"] == len(actions) and fit["first_step_mse"] < 0.5 * fit_short["first_step_mse"]
    # Its input scaling is the windows' statistics, and a chunk comes back in the env's action units.
    assert torch.allclose(policy.x_mean[:4], torch.tensor(states[:, :4].mean(0), dtype=torch.float32), rtol=0.05)
    chunk = policy.act(np.stack([states[0], states[0]]))
    assert chunk.shape == (16, 2)
    assert np.abs(chunk[0] - actions[0]).max() < np.abs(short.act(np.stack([states[0], states[0]]))[0]
                                                        - actions[0]).max() + 1e-6
    with pytest.raises(ValueError, match="warmup"):
        train_state_policy(pusht_demo_file, steps=10, warmup=20)


def test_state_rollouts_are_seeded_and_bounded(pusht_demo_file):
    policy, fit = train_state_policy(pusht_demo_file, steps=50, batch_size=32, warmup=5, seed=1)
    a = evaluate_state_policy(policy, fit["env_args"], episodes=2, seed=300)
    b = evaluate_state_policy(policy, fit["env_args"], episodes=2, seed=300)
    assert a == b
    assert 0.0 <= a["success_rate"] <= 1.0 and 0.0 <= a["mean_max_reward"] <= 1.0 and 1 <= a["mean_length"] <= 300
    with pytest.raises(ValueError, match="n_action_steps"):
        evaluate_state_policy(policy, fit["env_args"], episodes=1, seed=0, n_action_steps=17)


def test_ceiling_cli_prints_one_json_row(pusht_demo_file, capsys):
    assert main(["ceiling", "--dataset", str(pusht_demo_file), "--steps", "20", "--episodes", "1"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["train_seed"] == 0 and row["steps"] == 20 and row["episodes"] == 1 and row["seed"] == 200_000
    assert set(row) >= {"first_step_mse", "success_rate", "mean_max_reward", "windows", "dataset"}
