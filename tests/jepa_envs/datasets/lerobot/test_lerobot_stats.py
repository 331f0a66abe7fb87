"""meta/stats.json against numpy on the same values: image moments and quantiles from 256-bin histograms equal
numpy's over every pixel, and episode-by-episode combination equals one pass over all rows."""
from __future__ import annotations

import numpy as np

from jepa_envs.datasets.lerobot.stats import RunningStats


def test_image_stats_from_histograms_equal_numpy_over_every_pixel():
    rng = np.random.default_rng(0)
    episodes = [rng.integers(20, 230, (n, 12, 10, 3), dtype=np.uint8) for n in (5, 9, 3)]
    episodes[1][..., 2] = 7                                  # a constant channel: std 0, min = max
    stats = RunningStats(image=True)
    first = stats.add(episodes[0])
    pixels = np.concatenate([e.reshape(-1, 3) for e in episodes[:1]]).astype(np.float64) / 255
    assert np.allclose(first["mean"].ravel(), pixels.mean(0), atol=1e-12)
    assert np.allclose(first["std"].ravel(), pixels.std(0), atol=1e-12)
    for episode in episodes[1:]:
        stats.add(episode)
    pixels = np.concatenate([e.reshape(-1, 3) for e in episodes]).astype(np.float64) / 255
    out = stats.result()
    assert out["mean"].shape == (3, 1, 1) and out["count"].tolist() == [len(pixels)]
    for name, reference in (("mean", pixels.mean(0)), ("std", pixels.std(0)), ("min", pixels.min(0)),
                            ("max", pixels.max(0)), ("q50", np.quantile(pixels, 0.5, axis=0, method="inverted_cdf")),
                            ("q99", np.quantile(pixels, 0.99, axis=0, method="inverted_cdf"))):
        assert np.allclose(out[name].ravel(), reference, atol=1e-12), name


def test_vector_stats_combined_by_episode_equal_one_pass():
    rng = np.random.default_rng(1)
    episodes = [rng.normal(3.0, 2.0, (n, 4)) for n in (7, 1, 30)]
    stats = RunningStats()
    for episode in episodes:
        stats.add(episode)
    rows = np.concatenate(episodes)
    out = stats.result()
    assert np.allclose(out["mean"], rows.mean(0)) and np.allclose(out["std"], rows.std(0))
    assert np.allclose(out["q10"], np.quantile(rows, 0.10, axis=0)) and out["count"].tolist() == [len(rows)]
