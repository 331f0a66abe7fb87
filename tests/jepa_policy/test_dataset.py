"""Training windows: indices, boundary padding, batch layout, normalizer stats, resumable sampler."""
import numpy as np
import pytest
import torch

from jepa_policy.dataset import (ResumableBatchSampler, WindowDataset, make_loader, normalizer_stats, pixel_stats,
                                 window_indices)


def _toy(lengths=(5, 3), size=4):
    """Arrays whose values encode their own step index, so every gathered entry can be checked."""
    n = sum(lengths)
    steps = np.arange(n)
    obs = {
        "top_image": np.broadcast_to(steps[:, None, None, None], (n, size, size, 3)).astype(np.uint8),
        "agent_pos": np.stack([steps, -steps], axis=1).astype(np.float32),
    }
    actions = np.stack([steps, 10 * steps], axis=1).astype(np.float32)
    return obs, actions, np.cumsum(lengths)


def test_window_indices_pad_at_both_ends():
    idx = window_indices(np.array([5, 8]), obs_steps=2, horizon=4, future_k=2)
    assert idx.obs.shape == (8, 2) and idx.action.shape == (8, 4) and idx.future.shape == (8,)
    # first step of each episode repeats its first frame
    assert idx.obs[0].tolist() == [0, 0] and idx.obs[5].tolist() == [5, 5]
    assert idx.obs[3].tolist() == [2, 3]
    # actions a_t .. a_{t+H-1}; past the episode end the last action repeats (never the next episode's)
    assert idx.action[1].tolist() == [1, 2, 3, 4]
    assert idx.action[3].tolist() == [3, 4, 4, 4]
    assert idx.action[6].tolist() == [6, 7, 7, 7]
    # future frame o_{t+k}, clamped to the episode's last frame
    assert idx.future.tolist() == [2, 3, 4, 4, 4, 7, 7, 7]
    assert idx.episode.tolist() == [0] * 5 + [1] * 3


def test_window_indices_reject_bad_input():
    with pytest.raises(ValueError, match="strictly increasing"):
        window_indices(np.array([3, 3]), 2, 4, 1)
    with pytest.raises(ValueError, match="horizon"):
        window_indices(np.array([3]), 2, 0, 1)


def test_batch_gather_matches_indices_and_layout():
    obs, actions, ends = _toy()
    ds = WindowDataset(obs, actions, ends, ("top_image",), ("agent_pos",), obs_steps=2, horizon=4, future_k=2)
    batch = ds[[0, 3, 6]]
    assert batch["obs"]["top_image"].shape == (3, 2, 4, 4, 3) and batch["obs"]["top_image"].dtype == torch.uint8
    assert batch["obs"]["agent_pos"].shape == (3, 2, 2) and batch["obs"]["agent_pos"].dtype == torch.float32
    assert batch["future_obs"]["top_image"].shape == (3, 4, 4, 3)
    assert batch["action"].shape == (3, 4, 2)
    assert batch["obs"]["top_image"][:, :, 0, 0, 0].tolist() == [[0, 0], [2, 3], [5, 6]]
    assert batch["future_obs"]["top_image"][:, 0, 0, 0].tolist() == [2, 4, 7]
    assert batch["action"][:, :, 0].tolist() == [[0, 1, 2, 3], [3, 4, 4, 4], [6, 7, 7, 7]]
    single = ds[3]
    assert torch.equal(single["action"], batch["action"][1])


def test_dataset_names_missing_keys():
    obs, actions, ends = _toy()
    with pytest.raises(KeyError, match="wrist_image"):
        WindowDataset(obs, actions, ends, ("wrist_image",), ("agent_pos",), 2, 4, 2)


def test_normalizer_stats_are_min_max():
    obs, actions, _ = _toy()
    stats = normalizer_stats(actions, obs, ("agent_pos",))
    assert stats["action"]["min"].tolist() == [0, 0] and stats["action"]["max"].tolist() == [7, 70]
    assert stats["agent_pos"]["min"].tolist() == [0, -7] and stats["agent_pos"]["max"].tolist() == [7, 0]


def test_pixel_stats_are_the_exact_channel_mean_and_std():
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (7, 5, 6, 3), dtype=np.uint8)
    frames[..., 2] = 200                                     # a constant channel: std 0
    stats = pixel_stats(frames)
    x = frames.reshape(-1, 3).astype(np.float64) / 255.0
    assert np.allclose(stats["mean"], x.mean(0), atol=1e-6) and np.allclose(stats["std"], x.std(0), atol=1e-6)
    assert stats["std"][2] == 0.0
    obs, actions, _ = _toy()
    obs = {**obs, "top_image": frames}
    both = normalizer_stats(actions, obs, ("agent_pos",), ("top_image",))
    assert np.array_equal(both["top_image"]["mean"], stats["mean"]) and "min" in both["agent_pos"]
    with pytest.raises(ValueError, match="uint8 frames"):
        pixel_stats(frames.astype(np.float32))


def test_sampler_ranks_partition_the_global_batch_and_resume():
    single = ResumableBatchSampler(40, batch_size=8, seed=3)
    ranks = [ResumableBatchSampler(40, batch_size=8, seed=3, rank=r, world_size=2) for r in range(2)]
    it_single, it_ranks = iter(single), [iter(r) for r in ranks]
    seen = []
    for _ in range(12):  # crosses the epoch boundary (5 batches per epoch)
        glob = next(it_single)
        parts = [next(it) for it in it_ranks]
        assert sorted(glob) == sorted(parts[0] + parts[1])
        assert parts[0] == glob[0::2] and parts[1] == glob[1::2]
        seen.append(glob)
    assert sorted(sum(seen[:5], [])) == list(range(40))  # one epoch covers every window once
    resumed = ResumableBatchSampler(40, batch_size=8, seed=3)
    resumed.start_at(7)
    it = iter(resumed)
    assert [next(it) for _ in range(5)] == seen[7:12]


def test_loader_yields_batches():
    obs, actions, ends = _toy((20, 20))
    ds = WindowDataset(obs, actions, ends, ("top_image",), ("agent_pos",), 2, 4, 2)
    loader = make_loader(ds, ResumableBatchSampler(len(ds), 8, seed=0))
    batch = next(iter(loader))
    assert batch["action"].shape == (8, 4, 2)
    with pytest.raises(ValueError, match="fewer than one batch"):
        ResumableBatchSampler(4, 8, seed=0)
