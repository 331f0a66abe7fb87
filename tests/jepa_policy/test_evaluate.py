"""Evaluation: the NMSE formula, the Table 6 protocols, and real rollouts with consistent per-decision records."""
import numpy as np
import pytest

from jepa_policy.evaluate import nmse, reporting_protocols


def test_nmse_matches_hand_computation():
    z = np.array([[3.0, 4.0], [0.0, 0.0]])
    z_hat = np.array([[3.0, 2.0], [1.0, -1.0]])
    rms0 = np.sqrt((9 + 16) / 2)
    expected0 = ((0 / rms0) ** 2 + (2 / rms0) ** 2) / 2
    expected1 = ((1 / 1e-6) ** 2 + (1 / 1e-6) ** 2) / 2  # zero target: the 1e-6 floor of Sec. 3.3
    np.testing.assert_allclose(nmse(z_hat, z), [expected0, expected1], rtol=1e-12)
    assert nmse(z[0], z[0]) == 0.0
    with pytest.raises(ValueError, match="differs"):
        nmse(np.zeros(3), np.zeros(4))


def test_reporting_protocols_of_table_6():
    curve = [{"step": s, "success_rate": r} for s, r in
             [(30, 0.6), (10, 0.2), (20, 0.9), (40, 0.5), (50, 0.7), (60, 0.4), (70, 0.8)]]
    p = reporting_protocols(curve)
    assert p["best"] == 0.9
    assert p["last"] == 0.8                               # by step, not by list order
    assert p["mean_last5"] == pytest.approx(np.mean([0.6, 0.5, 0.7, 0.4, 0.8]))
    assert p["mean_all"] == pytest.approx(np.mean([0.2, 0.9, 0.6, 0.5, 0.7, 0.4, 0.8]))
    assert p["evaluations"] == 7
    with pytest.raises(ValueError, match="eval_every"):
        reporting_protocols([])
