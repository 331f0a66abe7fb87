"""Per-decision and per-episode future-consistency scores (paper Sec. 3.3, 3.6, 4.10)."""
from __future__ import annotations

import statistics
from collections.abc import Sequence

import numpy as np

RMS_FLOOR = 1e-6     # max(||z||_RMS, 1e-6) in d_NMSE (Sec. 3.3); the training loss uses the same constant
NMSE = "nmse"                 # the signal the service computes from the latents; never sent as a named score
RATIO = "nmse_ratio"          # the service's second built-in signal (``nmse_ratio``)
SERVICE_SIGNALS: tuple[str, ...] = (NMSE, RATIO)   # known at the target step t + k; never sent as named scores
PERSISTENCE_FLOOR = 1e-12     # a persistence NMSE at or below it has no ratio (rules.LOG_FLOOR, the same constant)


def nmse(z_hat: np.ndarray, z: np.ndarray) -> float:
    """Target-normalised MSE d_NMSE(z_hat, z) = ||(z_hat - z) / max(rms(z), 1e-6)||^2 / d_z (Sec. 3.3).

    Computed in float64 so the score does not depend on the float32 transport.
    """
    z_hat = np.asarray(z_hat, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if z_hat.shape != z.shape or z.ndim != 1:
        raise ValueError(f"nmse needs two 1-D latents of equal length, got {z_hat.shape} and {z.shape}")
    return float(nmse_rows(z_hat[None], z[None])[0])


def nmse_rows(z_hat: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``nmse`` of each row pair of two (n, d) arrays, in one pass over the batch (the ingest path scores a
    request's decisions together); float64.

    The one d_NMSE of the project. The monitor scores with it, and so do the policy's evaluation records, its
    server's replies and its retrieval audit (``jepa_policy`` may import this module; the monitor imports
    neither ``jepa_policy`` nor torch). The training loss ``jepa_policy.losses.nmse`` is the same formula in
    torch, because it must carry gradients on the training device in the autocast dtype; it shares
    ``RMS_FLOOR`` and a property test holds it to this function on random inputs
    (tests/jepa_policy/test_nmse_agreement.py).
    """
    z_hat, z = np.asarray(z_hat), np.asarray(z)
    if z_hat.shape != z.shape or z.ndim != 2:
        raise ValueError(f"nmse_rows needs two (n, d) arrays of equal shape, got {z_hat.shape} and {z.shape}")
    d = z.shape[1]
    # float64 copies, then einsum without a cast: bit-identical to casting inside einsum, and 1.3x quicker on a
    # 64 x 1024 float32 batch (einsum's casting loop is the slow part)
    z = z.astype(np.float64)
    mean_square = np.maximum(np.einsum("ij,ij->i", z, z) / d, RMS_FLOOR ** 2)
    diff = z_hat.astype(np.float64)
    diff -= z
    return np.einsum("ij,ij->i", diff, diff) / (mean_square * d)


def nmse_ratio(nmse_value, persistence):
    """``nmse_ratio`` = NMSE / persistence NMSE of the same decision (elementwise over arrays; float64): our error
    per unit of the scene's own change between t and t + k, known at the target step like NMSE. NaN (no value)
    where either is missing (None or NaN) or the persistence NMSE is at most ``PERSISTENCE_FLOOR``: z_t equals the
    target up to float32 rounding (a frozen scene), so there is no change to measure the error against, and a
    floored denominator would turn the frozen decisions into ~1e10 outliers. The one definition of the project:
    ``jepa-monitor compare``, the calibration and the live ingest path all call it."""
    nmse_value = np.asarray(np.nan if nmse_value is None else nmse_value, dtype=np.float64)
    persistence = np.asarray(np.nan if persistence is None else persistence, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = nmse_value / persistence
        return np.where((persistence > PERSISTENCE_FLOOR) & np.isfinite(ratio), ratio, np.nan)


def nmse_ratio_or_none(nmse_value: float | None, persistence: float | None) -> float | None:
    """``nmse_ratio`` of one decision as a float, None where it has none."""
    if nmse_value is None or persistence is None:
        return None
    ratio = float(nmse_ratio(nmse_value, persistence))
    return None if ratio != ratio else ratio


def early_score(scores_by_step: Sequence[float | None], n_first: int = 5) -> float | None:
    """Median NMSE of the episode's first ``n_first`` decisions (Sec. 4.10).

    ``scores_by_step`` holds the decisions in decision-step order, ``None`` where the realized target is not
    (yet) known. The episode counts only when all first ``n_first`` decisions have a valid target; otherwise
    the result is ``None``.
    """
    first = list(scores_by_step[:n_first])
    if len(first) < n_first or any(s is None for s in first):
        return None
    return float(statistics.median(map(float, first)))   # a few numbers: ~10x quicker than numpy's median


def running_score(scored: Sequence[float], window: int = 5) -> float | None:
    """Median of the most recent ``window`` scored decisions (the Sec. 3.6 sliding window); None before it fills."""
    if len(scored) < window:
        return None
    return float(statistics.median(map(float, scored[-window:])))
