"""Per-key affine normalisation of actions and low-dim inputs to [-1, 1] (``Normalizer``) and of camera pixels
to zero mean and unit variance per channel (``ImageStandardizer``), stored in the model's state_dict.

The statistics travel inside checkpoints, so a loaded policy normalises exactly as it was trained.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import nn

# A dimension whose range is below this is treated as constant and mapped to 0 rather than blown up.
MIN_RANGE = 1e-4
# A colour channel whose pixel std (in [0, 1] units) is below this is constant: centred, not scaled up.
MIN_PIXEL_STD = 1e-3


class _Affine(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("scale", torch.ones(dim))
        self.register_buffer("offset", torch.zeros(dim))


class Normalizer(nn.Module):
    """Holds ``y = x * scale + offset`` per key; ``set_stats`` fits it from min/max so that y spans [-1, 1]."""

    def __init__(self, dims: Mapping[str, int]):
        super().__init__()
        self.dims = dict(dims)
        self.fields = nn.ModuleDict({k: _Affine(d) for k, d in self.dims.items()})
        self.register_buffer("fitted", torch.tensor(False))

    def set_stats(self, stats: Mapping[str, Mapping[str, np.ndarray]]) -> None:
        """Fit from ``{key: {"min": array, "max": array}}``; every key of the model must be present."""
        missing = [k for k in self.dims if k not in stats]
        if missing:
            raise ValueError(f"normalizer stats lack key(s) {missing}; give min/max for every one of "
                             f"{list(self.dims)}")
        for key, dim in self.dims.items():
            entry = stats[key]
            if "min" not in entry or "max" not in entry:
                raise ValueError(f"normalizer stats for {key!r} need both 'min' and 'max' arrays")
            lo = np.asarray(entry["min"], dtype=np.float64).reshape(-1)
            hi = np.asarray(entry["max"], dtype=np.float64).reshape(-1)
            if lo.shape != (dim,) or hi.shape != (dim,):
                raise ValueError(f"normalizer stats for {key!r} have shapes {lo.shape}/{hi.shape}; expected ({dim},)")
            if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
                raise ValueError(f"normalizer stats for {key!r} contain NaN or inf; clean the dataset first")
            if (hi < lo).any():
                raise ValueError(f"normalizer stats for {key!r} have max < min in some dimension")
            rng = hi - lo
            constant = rng < MIN_RANGE
            scale = np.where(constant, 1.0, 2.0 / np.where(constant, 1.0, rng))
            offset = np.where(constant, -(lo + hi) / 2.0, -1.0 - lo * scale)
            f = self.fields[key]
            f.scale.copy_(torch.as_tensor(scale, dtype=f.scale.dtype))
            f.offset.copy_(torch.as_tensor(offset, dtype=f.offset.dtype))
        self.fitted.fill_(True)

    def _check(self, key: str) -> _Affine:
        if not bool(self.fitted):
            raise RuntimeError("the normalizer has no statistics; call model.set_normalizer_stats(stats) "
                               "with the dataset's statistics from jepa_policy.dataset.normalizer_stats (or load a "
                               "trained checkpoint)")
        if key not in self.fields:
            raise KeyError(f"normalizer has no key {key!r}; it knows {list(self.fields)}")
        return self.fields[key]

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        f = self._check(key)
        return x * f.scale + f.offset

    def unnormalize(self, key: str, y: torch.Tensor) -> torch.Tensor:
        f = self._check(key)
        return (y - f.offset) / f.scale


class ImageStandardizer(Normalizer):
    """Per camera and colour channel ``(x - mean) / std`` of pixels in [0, 1], fitted from the training frames.

    Used when ``ModelConfig.image_norm == "dataset"``. Fed as [0, 1], a mostly uniform scene (PushT: channel
    means about 0.91, stds about 0.09) makes every conv filter's response mostly the background times the
    filter's weight sum, a constant per channel that the one-group GroupNorm of a narrow encoder does not remove;
    standardised, the filters start on the scene's structure (measured in docs/training.md). It is a
    ``Normalizer`` over the 3 channels of each image key (scale = 1 / std, offset = -mean / std), so
    ``normalize(key, x)`` takes channel-last pixels (..., h, w, 3); only the fit differs.
    """

    def __init__(self, keys: tuple[str, ...]):
        super().__init__({k: 3 for k in keys})

    def set_stats(self, stats: Mapping[str, Mapping[str, np.ndarray]]) -> None:
        """Fit from ``{image_key: {"mean": (3,), "std": (3,)}}`` in [0, 1] pixel units, one entry per camera."""
        missing = [k for k in self.dims if k not in stats or not {"mean", "std"} <= set(stats[k])]
        if missing:
            raise ValueError(f"normalizer stats lack the pixel mean/std of image key(s) {missing}, which "
                             "image_norm='dataset' needs; compute them with jepa_policy.dataset.normalizer_stats("
                             "actions, obs, lowdim_keys, image_keys) or set image_norm='unit'")
        for key in self.dims:
            mean = np.asarray(stats[key]["mean"], dtype=np.float64).reshape(-1)
            std = np.asarray(stats[key]["std"], dtype=np.float64).reshape(-1)
            if mean.shape != (3,) or std.shape != (3,):
                raise ValueError(f"pixel stats for {key!r} have shapes {mean.shape}/{std.shape}; expected (3,) "
                                 "(one value per RGB channel)")
            if not (np.isfinite(mean).all() and np.isfinite(std).all()) or (std < 0).any():
                raise ValueError(f"pixel stats for {key!r} must be finite with std >= 0; got mean {mean}, "
                                 f"std {std}")
            std = np.where(std < MIN_PIXEL_STD, 1.0, std)
            f = self.fields[key]
            f.scale.copy_(torch.as_tensor(1.0 / std, dtype=f.scale.dtype))
            f.offset.copy_(torch.as_tensor(-mean / std, dtype=f.offset.dtype))
        self.fitted.fill_(True)
