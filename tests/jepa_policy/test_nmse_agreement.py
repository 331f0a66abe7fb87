"""One d_NMSE (Sec. 3.3): the training loss, the evaluation records, the retrieval audit, the policy server and the
monitor all compute ``monitor_service.scoring.nmse_rows`` (the torch loss as the same formula with gradients), and
agree with the paper's formula on random latents, targets below the RMS floor included."""
from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from jepa_policy import audit, evaluate, losses
from jepa_policy.serve import server
from monitor_service import scoring


def paper_nmse(z_hat: np.ndarray, z: np.ndarray) -> np.ndarray:
    """||(z_hat - z) / max(||z||_RMS, 1e-6)||^2 / d_z per row, written out as the paper writes it."""
    z_hat, z = np.asarray(z_hat, np.float64), np.asarray(z, np.float64)
    rms = np.sqrt(np.mean(z ** 2, axis=-1, keepdims=True))
    return np.sum(((z_hat - z) / np.maximum(rms, 1e-6)) ** 2, axis=-1) / z.shape[-1]


# float64 results below its smallest normal number are subnormal and carry no relative precision (a value of
# 4e-315 computed as 0 by another order of the same operations): agreement there is absolute, at that level
TINY = np.finfo(np.float64).tiny


@st.composite
def latent_pairs(draw):
    """(n, d) predictions and targets; the target's scale spans the floor (1e-9) to large latents (1e3)."""
    n, d = draw(st.integers(1, 6)), draw(st.integers(1, 40))
    values = st.floats(-10, 10, allow_nan=False, allow_subnormal=False)
    z_hat = draw(arrays(np.float64, (n, d), elements=values))
    z = draw(arrays(np.float64, (n, d), elements=values))
    scale = 10.0 ** draw(st.integers(-9, 3))
    return z_hat * scale, z * scale


@settings(max_examples=200, deadline=None)
@given(latent_pairs())
def test_every_nmse_of_the_project_agrees_on_random_latents(pair):
    z_hat, z = pair
    reference = paper_nmse(z_hat, z)
    rows = scoring.nmse_rows(z_hat, z)
    np.testing.assert_allclose(rows, reference, rtol=1e-12, atol=TINY)
    np.testing.assert_allclose([scoring.nmse(a, b) for a, b in zip(z_hat, z)], reference, rtol=1e-12, atol=TINY)
    # the training loss, in float64 (the formula) and in float32 (how it trains)
    per_sample = losses.nmse(torch.from_numpy(z_hat), torch.from_numpy(z), reduction="none").numpy()
    np.testing.assert_allclose(per_sample, reference, rtol=1e-12, atol=TINY)
    mean = losses.nmse(torch.from_numpy(z_hat), torch.from_numpy(z)).item()
    np.testing.assert_allclose(mean, reference.mean(), rtol=1e-12, atol=TINY)
    single = losses.nmse(torch.from_numpy(z_hat).float(), torch.from_numpy(z).float(), reduction="none").numpy()
    np.testing.assert_allclose(single, paper_nmse(z_hat.astype(np.float32), z.astype(np.float32)), rtol=2e-4,
                               atol=1e-6)   # float32 loses what lies below its resolution, nothing else
    # the retrieval audit: every query against every candidate
    matrix = audit.nmse_matrix(z_hat, np.repeat(z[None], len(z_hat), axis=0))
    np.testing.assert_allclose(matrix, paper_nmse(z_hat[:, None, :], z[None, :, :]), rtol=1e-12, atol=TINY)


def test_the_policy_scores_with_the_monitors_function():
    """Evaluation records and server replies call the monitor's d_NMSE itself, not a copy of it."""
    assert evaluate.nmse_rows is scoring.nmse_rows
    assert server.nmse is scoring.nmse
    assert losses.RMS_FLOOR is scoring.RMS_FLOOR
    assert not hasattr(evaluate, "nmse"), "jepa_policy.evaluate defines its own d_NMSE again"
