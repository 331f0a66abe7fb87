"""A model trained with a future horizon k other than its task spec's (``--model '{"future_k": 8}'``) is trained,
scored and fitted against o_{t+k} of ITS k everywhere: training windows, the acting runtime's target step and
rendered frames, rollout records, and the detectors' training prediction errors (PushT's spec says k = 4)."""
import numpy as np
import pytest
import torch

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_policy.dataset import WindowDataset
from jepa_policy.detectors import training_embeddings
from jepa_policy.evaluate import evaluate
from jepa_policy.policy import Policy
from jepa_policy.train import TrainingData, load_config, train

K = 8


@pytest.fixture(scope="module")
def demos(pusht_demo_file):
    return load_dataset(pusht_demo_file, task="PushT", image_size=32)


@pytest.fixture(scope="module")
def k8(demos, tmp_path_factory):
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path_factory.mktemp("k8")), steps=2, warmup_steps=1,
                      model={"future_k": K})
    return cfg, train(cfg, demos)["checkpoint"]


def test_training_windows_target_the_models_horizon(demos, k8):
    assert demos.spec.future_k == 4                      # the override differs from the spec
    index = TrainingData.of(k8[0], demos).windows.index
    t = index.obs[:, -1]
    assert np.array_equal(index.future[~index.clamped], t[~index.clamped] + K)
    assert index.clamped.sum() == len(demos.episode_ends) * K


def test_policy_scores_against_the_frame_k_steps_ahead_and_renders_it(k8):
    policy = Policy.from_checkpoint(k8[1], detectors=False)
    assert policy.model.cfg.future_k == K and policy.k == K
    # k = 8 = the decision period: the future targets are decision frames, frame 4 (k = 4's target) is not needed
    assert [s for s in range(24) if policy.images_needed(s)] == [0, 7, 8, 15, 16, 23]
    records = evaluate(policy, episodes=1, seed=5, num_envs=1, max_steps=20)["records"][0]["decisions"]
    assert [(d["step"], d["target_step"]) for d in records] == [(0, 8), (8, 16), (16, 24)]
    assert records[0]["nmse"] is not None and records[1]["nmse"] is not None and records[2]["nmse"] is None


def test_detector_prediction_errors_use_the_models_horizon(demos, k8):
    policy = Policy.from_checkpoint(k8[1], detectors=False)
    c, errors = training_embeddings(policy, demos, samples=64, seed=3)
    windows = WindowDataset.from_demos(demos, future_k=K)
    idx = np.sort(np.random.default_rng(3).choice(len(windows), size=64, replace=False))
    batch = windows[idx]
    with torch.inference_mode():
        z_hat = policy.model.representations(batch["obs"])["z_hat"]
        want = (z_hat - policy.model.encode_future(batch["future_obs"])).double().numpy()
    np.testing.assert_allclose(errors, want, rtol=1e-5, atol=1e-6)
