"""Representation-collapse audit (paper Sec. 4.9): spectral statistics of latents, computed in float64.

For a representation matrix X (N samples x D features), centred over samples, with eigenvalues
lambda_1 >= ... >= lambda_D of X_c^T X_c:
- effective rank = exp(entropy of lambda / sum(lambda))  (Roy & Vetterli), between 1 and D;
- top-eigenvalue share = lambda_1 / sum(lambda);
- TE32 = 1 - sum_{i<=32} lambda_i / sum(lambda): spectral energy outside the leading 32 directions; the
  paper's pre-specified low-rank boundary is TE32 = 0.05.
The checkpoint audit encodes a fixed manifest of dataset windows (seeded choice of up to 4,096) with the
EMA policy and reports these statistics for the encoder latents z = E_rgb(o) and the predictor's z_hat.
"""
from __future__ import annotations

import numpy as np
import torch

from jepa_policy.dataset import WindowDataset

TE32_BOUNDARY = 0.05


def centred_spectrum(x: np.ndarray) -> np.ndarray:
    """Eigenvalues of X_c^T X_c in descending order (float64), via the singular values of X_c."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need a (N >= 2, D) representation matrix, got shape {x.shape}")
    xc = x - x.mean(axis=0, keepdims=True)
    s = np.linalg.svd(xc, compute_uv=False)
    return np.sort(s * s)[::-1]


def spectral_stats(x: np.ndarray, k: int = 32) -> dict:
    """Effective rank, top-eigenvalue share and TE_k of the centred matrix (Sec. 4.9)."""
    lam = centred_spectrum(x)
    total = lam.sum()
    if total <= 0:  # every sample identical: complete collapse
        return {"effective_rank": 1.0, "top_share": 1.0, f"te{k}": 0.0, "dim": int(np.asarray(x).shape[1]),
                "low_rank": True}
    p = lam / total
    nz = p[p > 0]
    te = float(1.0 - p[:k].sum())
    return {"effective_rank": float(np.exp(-(nz * np.log(nz)).sum())), "top_share": float(p[0]),
            f"te{k}": te, "dim": int(np.asarray(x).shape[1]), "low_rank": te < TE32_BOUNDARY}


def manifest(num_windows: int, samples: int = 4096, seed: int = 0) -> np.ndarray:
    """Fixed, sorted sample of window indices, so every checkpoint is audited on the same inputs."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(num_windows, size=min(samples, num_windows), replace=False))


@torch.inference_mode()
def audit_checkpoint(policy, demos, samples: int = 4096, seed: int = 0, batch_size: int = 256) -> dict:
    """Spectral statistics of encoder latents E_rgb(o_t) and predicted z_hat on a fixed manifest of windows."""
    windows = WindowDataset.from_demos(demos)
    idx = manifest(len(windows), samples, seed)
    model, device = policy.model, policy.device
    z_enc, z_hat = [], []
    for start in range(0, len(idx), batch_size):
        batch = windows[idx[start:start + batch_size]]
        obs = {k: v.to(device) for k, v in batch["obs"].items()}
        newest = {k: obs[k][:, -1] for k in policy.spec.image_keys}
        z_enc.append(model.encode_future(newest).double().cpu().numpy())
        _, zh = model.predict(obs, want_future=True)
        if zh is not None:
            z_hat.append(zh.double().cpu().numpy())
    report = {"samples": int(len(idx)), "seed": seed, "encoder": spectral_stats(np.concatenate(z_enc))}
    if z_hat:
        report["predictor"] = spectral_stats(np.concatenate(z_hat))
    return report
