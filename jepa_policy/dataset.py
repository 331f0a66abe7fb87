"""Training windows over demonstrations: observation history, action chunk and future frame (Sec. 3.1).

Indexing. The paper writes the target chunk as a_{t:t+H} = (a_{t+1}, ..., a_{t+H}), counting an action by the
state it leads to. In the arrays of a demonstration, ``actions[t]`` is the action executed after observing
``obs[t]`` (the one that produces ``obs[t+1]``), so the paper's a_{t+1} is ``actions[t]`` and a window whose
newest frame is ``obs[t]`` uses ``actions[t : t+H]``, exactly as diffusion_policy's SequenceSampler does.
The future target o_{t+k} is ``obs[t+k]``: k environment steps after the newest observation frame (Sec. 4.1).

Padding at episode boundaries (as in diffusion_policy): observation frames before the episode start repeat
the first frame; actions after the episode end repeat the last action (the robot holds its final pose);
the future frame is clamped to the episode's last frame.

Every window is a set of integer indices into the concatenated arrays, precomputed once, so a batch is a
handful of numpy fancy-indexing operations and no per-sample Python work or image decoding.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset, DistributedSampler, Sampler


@dataclass(frozen=True)
class WindowIndex:
    """Integer indices of every training window into the concatenated demonstration arrays."""

    obs: np.ndarray      # (N, obs_steps) frames t-obs_steps+1 .. t
    action: np.ndarray   # (N, horizon) actions t .. t+H-1
    future: np.ndarray   # (N,) frame t+k
    episode: np.ndarray  # (N,) episode of each window
    clamped: np.ndarray  # (N,) bool: t+k lies past the episode's end, so the future frame is its last one


def window_indices(episode_ends: np.ndarray, obs_steps: int, horizon: int, future_k: int) -> WindowIndex:
    """One window per time step t of every episode, with the padding rules of the module docstring."""
    ends = np.asarray(episode_ends, dtype=np.int64)
    if ends.ndim != 1 or len(ends) == 0:
        raise ValueError("episode_ends must be a non-empty 1-D array of cumulative episode ends")
    starts = np.concatenate([[0], ends[:-1]])
    if np.any(ends <= starts):
        raise ValueError(f"episode_ends must be strictly increasing and every episode non-empty; got {ends[:10]}")
    if obs_steps < 1 or horizon < 1 or future_k < 0:
        raise ValueError(f"need obs_steps >= 1, horizon >= 1, future_k >= 0; got {obs_steps}, {horizon}, {future_k}")
    lengths = ends - starts
    t = np.arange(ends[-1], dtype=np.int64)                       # newest frame of each window
    ep = np.repeat(np.arange(len(ends)), lengths)
    lo, hi = starts[ep][:, None], (ends[ep] - 1)[:, None]
    obs = np.clip(t[:, None] + np.arange(-(obs_steps - 1), 1), lo, hi)
    action = np.clip(t[:, None] + np.arange(horizon), lo, hi)
    future = np.minimum(t + future_k, hi[:, 0])
    return WindowIndex(obs=obs, action=action, future=future, episode=ep, clamped=t + future_k > hi[:, 0])


class WindowDataset(Dataset):
    """Windows (obs history, action chunk, future frame) in the batch layout of ``model.compute_loss``.

    ``dataset[i]`` gives one window; ``dataset[list_of_indices]`` gives a whole batch in one gather, which is
    what ``make_loader`` uses. Images stay uint8 (the model crops and scales them).
    """

    def __init__(self, obs: dict[str, np.ndarray], actions: np.ndarray, episode_ends: np.ndarray,
                 image_keys: tuple[str, ...], lowdim_keys: tuple[str, ...],
                 obs_steps: int, horizon: int, future_k: int):
        missing = [k for k in (*image_keys, *lowdim_keys) if k not in obs]
        if missing:
            raise KeyError(f"dataset lacks observation keys {missing}; it has {sorted(obs)}. "
                           "Check that the dataset was made for this task.")
        n = len(actions)
        for key in (*image_keys, *lowdim_keys):
            if len(obs[key]) != n:
                raise ValueError(f"obs[{key!r}] has {len(obs[key])} rows but actions has {n}")
        if int(episode_ends[-1]) != n:
            raise ValueError(f"episode_ends[-1] = {int(episode_ends[-1])} but the dataset has {n} steps")
        self.obs = {k: obs[k] for k in (*image_keys, *lowdim_keys)}
        self.actions = np.asarray(actions, dtype=np.float32)
        self.image_keys, self.lowdim_keys = tuple(image_keys), tuple(lowdim_keys)
        self.index = window_indices(episode_ends, obs_steps, horizon, future_k)

    @classmethod
    def from_demos(cls, demos, obs_steps: int | None = None, horizon: int | None = None,
                   future_k: int | None = None) -> "WindowDataset":
        """Windows over a ``jepa_envs.datasets.hdf5.DemoDataset``; unset sizes come from its task spec."""
        spec = demos.spec
        return cls(demos.obs, demos.actions, demos.episode_ends, spec.image_keys, spec.lowdim_keys,
                   obs_steps or spec.obs_steps, horizon or spec.horizon,
                   spec.future_k if future_k is None else future_k)

    def __len__(self) -> int:
        return len(self.index.future)

    def __getitem__(self, i):
        idx = np.asarray(i, dtype=np.int64)
        obs_idx, act_idx, fut_idx = self.index.obs[idx], self.index.action[idx], self.index.future[idx]
        return {
            "obs": {k: torch.from_numpy(np.ascontiguousarray(self.obs[k][obs_idx]))
                    for k in (*self.image_keys, *self.lowdim_keys)},
            "future_obs": {k: torch.from_numpy(np.ascontiguousarray(self.obs[k][fut_idx]))
                           for k in self.image_keys},
            "action": torch.from_numpy(self.actions[act_idx]),
        }


def normalizer_stats(actions: np.ndarray, obs: dict[str, np.ndarray], lowdim_keys, image_keys=()) -> dict:
    """The format of ``set_normalizer_stats``: per-dimension min/max of the actions and every low-dim input, and
    per-channel pixel mean/std (in [0, 1] units) of every image key given."""
    stats = {"action": {"min": np.min(actions, axis=0).astype(np.float32),
                        "max": np.max(actions, axis=0).astype(np.float32)}}
    for key in lowdim_keys:
        stats[key] = {"min": np.min(obs[key], axis=0).astype(np.float32),
                      "max": np.max(obs[key], axis=0).astype(np.float32)}
    for key in image_keys:
        stats[key] = pixel_stats(obs[key])
    return stats


def pixel_stats(frames: np.ndarray) -> dict:
    """Exact per-channel mean and std of uint8 HWC frames (..., 3), in [0, 1] units, from 256-bin histograms."""
    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim < 3 or frames.shape[-1] != 3 or frames.size == 0:
        raise ValueError(f"pixel stats need non-empty uint8 frames of shape (..., h, w, 3); got {frames.dtype} "
                         f"{frames.shape}")
    levels = np.arange(256, dtype=np.float64) / 255.0
    mean, std = np.empty(3), np.empty(3)
    for c in range(3):
        counts = np.bincount(frames[..., c].ravel(), minlength=256).astype(np.float64)
        p = counts / counts.sum()
        mean[c] = p @ levels
        std[c] = np.sqrt(max(p @ (levels - mean[c]) ** 2, 0.0))
    return {"mean": mean.astype(np.float32), "std": std.astype(np.float32)}


class ResumableBatchSampler(Sampler):
    """Shuffled per-rank batches that can restart mid-epoch.

    Built on ``DistributedSampler`` (same permutation for every world size, seeded by seed + epoch), so the
    union of the ranks' batch b is the single-process global batch b: rank r holds its positions r::world.
    ``start_at(step)`` makes a resumed run continue with the batch it would have drawn next.
    """

    def __init__(self, num_samples: int, batch_size: int, seed: int, rank: int = 0, world_size: int = 1):
        if batch_size % world_size:
            raise ValueError(f"global batch {batch_size} must be divisible by the world size {world_size}")
        self.local_batch = batch_size // world_size
        if num_samples < batch_size:
            raise ValueError(f"dataset has {num_samples} windows, fewer than one batch of {batch_size}; "
                             "lower batch_size or record more demonstrations")
        self._inner = DistributedSampler(range(num_samples), num_replicas=world_size, rank=rank,
                                         shuffle=True, seed=seed, drop_last=True)
        self.epoch, self.batches_taken = 0, 0

    def batches_per_epoch(self) -> int:
        return len(self._inner) // self.local_batch

    def __len__(self) -> int:
        return self.batches_per_epoch()

    def __iter__(self):
        """Endless stream of index lists; the training loop decides when to stop."""
        while True:
            self._inner.set_epoch(self.epoch)
            order = list(self._inner)
            while self.batches_taken < self.batches_per_epoch():
                b = self.batches_taken
                self.batches_taken += 1
                yield order[b * self.local_batch:(b + 1) * self.local_batch]
            self.epoch, self.batches_taken = self.epoch + 1, 0

    def position(self) -> dict:
        """Where the next batch comes from: (epoch, batches of that epoch already taken)."""
        return {"epoch": self.epoch, "batches_taken": self.batches_taken}

    def start_at(self, batches_consumed: int) -> None:
        """Continue after ``batches_consumed`` batches. The training loop passes its step count, not the
        sampler's own counter, because a DataLoader with workers draws batches ahead of their use."""
        self.epoch, self.batches_taken = divmod(int(batches_consumed), self.batches_per_epoch())


def make_loader(dataset: WindowDataset, sampler: ResumableBatchSampler, num_workers: int = 0,
                pin_memory: bool = False) -> torch.utils.data.DataLoader:
    """DataLoader that gathers one whole batch per fetch (batch_size=None: the sampler yields index lists)."""
    return torch.utils.data.DataLoader(dataset, sampler=sampler, batch_size=None, num_workers=num_workers,
                                       pin_memory=pin_memory, persistent_workers=num_workers > 0)
