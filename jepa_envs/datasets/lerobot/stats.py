"""meta/stats.json as LeRobot computes it: per feature min, max, mean, std, count and quantiles, combined
episode by episode (each episode's own statistics go into its meta/episodes row)."""
from __future__ import annotations

import numpy as np

from jepa_envs.datasets.lerobot.format import QUANTILES


class RunningStats:
    """min, max, mean, std over the rows of one vector feature, combined episode by episode; quantiles from the
    values themselves (vector features are small) or, for uint8 images, exactly from 256-bin histograms."""

    def __init__(self, image: bool = False):
        self.image = image
        self.count = 0
        self.mean = self.m2 = self.min = self.max = None
        self.values: list[np.ndarray] = []
        self.histogram: np.ndarray | None = None

    def add(self, x: np.ndarray) -> dict:
        """Add one episode's rows (T, D) or frames (T, H, W, 3); returns that episode's own statistics."""
        if self.image:
            hist = np.stack([np.bincount(x[..., c].ravel(), minlength=256) for c in range(x.shape[-1])])
            self.histogram = hist if self.histogram is None else self.histogram + hist
            episode = _hist_moments(hist)
            episode.update(_hist_quantiles(hist))
            episode = {k: (np.asarray(v).reshape(-1, 1, 1) if k != "count" else v) for k, v in episode.items()}
        else:
            flat = x.reshape(len(x), -1).astype(np.float64)
            self.values.append(flat)
            episode = _moments(flat)
            episode.update({f"q{int(round(q * 100)):02d}": np.quantile(flat, q, axis=0) for q in QUANTILES})
        n, mean, m2 = episode["count"][0], _flat(episode["mean"]), _flat(episode["m2"])
        if self.count == 0:
            self.mean, self.m2 = mean, m2
            self.min, self.max = _flat(episode["min"]), _flat(episode["max"])
        else:   # Chan et al.: combine two (count, mean, M2) summaries
            total = self.count + n
            delta = mean - self.mean
            self.mean = self.mean + delta * n / total
            self.m2 = self.m2 + m2 + delta ** 2 * self.count * n / total
            self.min = np.minimum(self.min, _flat(episode["min"]))
            self.max = np.maximum(self.max, _flat(episode["max"]))
        self.count += n
        episode.pop("m2")
        return episode

    def result(self) -> dict:
        out = {"min": self.min, "max": self.max, "mean": self.mean, "std": np.sqrt(self.m2 / self.count),
               "count": np.array([self.count])}
        if self.image:
            out.update(_hist_quantiles(self.histogram))
            return {k: (np.asarray(v).reshape(-1, 1, 1) if k != "count" else v) for k, v in out.items()}
        values = np.concatenate(self.values)
        out.update({f"q{int(round(q * 100)):02d}": np.quantile(values, q, axis=0) for q in QUANTILES})
        return out


def _flat(v) -> np.ndarray:
    return np.asarray(v, np.float64).reshape(-1)


def _moments(flat: np.ndarray) -> dict:
    mean = flat.mean(axis=0)
    return {"min": flat.min(axis=0), "max": flat.max(axis=0), "mean": mean, "std": flat.std(axis=0),
            "count": np.array([len(flat)]), "m2": ((flat - mean) ** 2).sum(axis=0)}


def _hist_moments(hist: np.ndarray) -> dict:
    """The moments of uint8 values per channel, in [0, 1], from their 256-bin counts: exact, and without the
    float64 copy of every pixel that made them most of an export's time."""
    values = np.arange(hist.shape[1]) / 255.0
    count = hist.sum(axis=1)
    mean = hist @ values / count
    m2 = (hist * (values[None, :] - mean[:, None]) ** 2).sum(axis=1)
    seen = hist > 0
    return {"min": values[np.argmax(seen, axis=1)], "max": values[hist.shape[1] - 1 - np.argmax(seen[:, ::-1], axis=1)],
            "mean": mean, "std": np.sqrt(m2 / count), "count": np.array([int(count[0])]), "m2": m2}


def _hist_quantiles(hist: np.ndarray) -> dict:
    """Exact quantiles of uint8 values per channel from their 256-bin counts, in [0, 1]."""
    cdf = np.cumsum(hist, axis=1) / hist.sum(axis=1, keepdims=True)
    return {f"q{int(round(q * 100)):02d}": np.argmax(cdf >= q, axis=1) / 255.0 for q in QUANTILES}


def episode_stats(key: str, stats: dict) -> dict:
    """One episode's statistics as its meta/episodes columns (``stats/<feature>/<name>``)."""
    return {f"stats/{key}/{name}": np.asarray(value).tolist() for name, value in stats.items()}
