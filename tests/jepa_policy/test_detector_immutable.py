"""``EmbeddingDetectors.score`` caches a fused matrix built from the fitted arrays on its first call. Before, the
object stayed mutable: a field reassigned (``det.std = ...``) or an array changed in place after the first score
was silently ignored by every score but the centring on ``mean`` (a stale mix). Now the fields are frozen and the
arrays read-only; ``dataclasses.replace`` gives a changed copy with its own cache. A row of the wrong shape is a
one-line error, not numpy's IndexError or broadcast message."""
import dataclasses

import numpy as np
import pytest

from jepa_policy.detectors import fit_embedding_detectors, load_detectors


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    rng = np.random.default_rng(0)
    c = rng.normal(size=(160, 8)) @ rng.normal(size=(8, 8)) + 5.0
    det = fit_embedding_detectors(c, clusters=4, seed=0)
    return det, load_detectors(det.save(tmp_path_factory.mktemp("immutable") / "d.npz")), c[:6]


def test_fitted_and_loaded_detectors_cannot_change_under_their_cache(fitted):
    det, loaded, rows = fitted
    for d in (det, loaded):
        before = d.score(rows)
        with pytest.raises(dataclasses.FrozenInstanceError):
            d.std = d.std * 2
        for array in (d.mean, d.std, d.whiten, d.pca, d.centres, d.rnd_target[0][0], d.rnd_predictor[-1][1]):
            with pytest.raises(ValueError, match="read-only"):
                array[...] = 0
        moved = dataclasses.replace(d, centres=d.centres + 1.0)   # a changed copy is scored by its own arrays
        assert not np.allclose(moved.score(rows)["pca_kmeans"], before["pca_kmeans"])
        np.testing.assert_array_equal(d.score(rows)["pca_kmeans"], before["pca_kmeans"])


@pytest.mark.parametrize("shape", [(8,), (3, 7), (2, 3, 8)])
def test_a_row_of_the_wrong_shape_is_a_clear_error(fitted, shape):
    with pytest.raises(ValueError, match=r"score needs c_t rows of shape \(B, 8\), got"):
        fitted[0].score(np.zeros(shape))
