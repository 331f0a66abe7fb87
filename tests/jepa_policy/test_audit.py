"""Collapse audit statistics (Sec. 4.9) against direct eigen-decompositions and known spectra."""
import numpy as np
import pytest

from jepa_policy.audit import centred_spectrum, manifest, spectral_stats


def test_spectrum_equals_eigenvalues_of_centred_gram():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 40)) @ rng.normal(size=(40, 40)) + 5.0
    xc = x - x.mean(0)
    expected = np.sort(np.linalg.eigvalsh(xc.T @ xc))[::-1]
    np.testing.assert_allclose(centred_spectrum(x), expected, rtol=1e-9, atol=1e-9)


def test_stats_on_known_spectra():
    rng = np.random.default_rng(1)
    # 64 orthogonal directions with equal energy: effective rank 64, top share 1/64, TE32 = 1/2
    q, _ = np.linalg.qr(rng.normal(size=(64, 64)))
    x = np.concatenate([q, -q]) * 3.0
    s = spectral_stats(x)
    assert s["effective_rank"] == pytest.approx(64.0, rel=1e-9)
    assert s["top_share"] == pytest.approx(1 / 64, rel=1e-9)
    assert s["te32"] == pytest.approx(0.5, rel=1e-9) and not s["low_rank"]
    # rank one plus a constant offset: complete concentration in one direction
    line = np.outer(rng.normal(size=100), rng.normal(size=16)) + 7.0
    s = spectral_stats(line)
    assert s["effective_rank"] == pytest.approx(1.0, abs=1e-6) and s["top_share"] == pytest.approx(1.0)
    assert s["te32"] == pytest.approx(0.0, abs=1e-12) and s["low_rank"]
    # identical samples: the degenerate case is reported as collapsed, not as NaN
    assert spectral_stats(np.ones((10, 8)))["low_rank"]
    with pytest.raises(ValueError, match="representation matrix"):
        spectral_stats(np.ones(5))


def test_manifest_is_fixed_and_bounded():
    a, b = manifest(10_000, 4096, seed=3), manifest(10_000, 4096, seed=3)
    assert np.array_equal(a, b) and len(np.unique(a)) == 4096 and a.max() < 10_000
    assert len(manifest(100, 4096)) == 100
