"""Rotation conversions: round trips, agreement with closed-form formulas, the angle-pi corner, bad input."""
import numpy as np
import pytest

from jepa_envs.tasks import rotations as R


def _random_matrices(n, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return R.quat_to_matrix(q)


def _rodrigues(v):
    """Closed-form axis-angle -> matrix, the reference the library calls are checked against."""
    angle = np.linalg.norm(v)
    k = v / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def test_matrices_are_rotations():
    m = _random_matrices(100)
    np.testing.assert_allclose(m @ np.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)


def test_axis_angle_matches_rodrigues_and_robosuite_quaternion_convention():
    v = np.array([0.3, -1.2, 0.5])
    np.testing.assert_allclose(R.axis_angle_to_matrix(v), _rodrigues(v), atol=1e-12)
    # robosuite: q = (axis * sin(angle / 2), cos(angle / 2)), scalar last
    angle = np.linalg.norm(v)
    expected = np.concatenate([v / angle * np.sin(angle / 2), [np.cos(angle / 2)]])
    np.testing.assert_allclose(R.axis_angle_to_quat(v), expected, atol=1e-12)


def test_rot6d_is_first_two_columns_and_round_trips():
    m = _random_matrices(200, seed=1)
    r6 = R.matrix_to_rot6d(m)
    assert r6.shape == (200, 6)
    np.testing.assert_allclose(r6[:, :3], m[:, :, 0])
    np.testing.assert_allclose(r6[:, 3:], m[:, :, 1])
    np.testing.assert_allclose(R.rot6d_to_matrix(r6), m, atol=1e-12)


def test_rot6d_gram_schmidt_accepts_unnormalised_input():
    m = _random_matrices(10, seed=2)
    r6 = R.matrix_to_rot6d(m)
    noisy = r6 * 3.0 + np.concatenate([np.zeros((10, 3)), 0.5 * r6[:, :3]], axis=1)  # scale, skew col 2
    np.testing.assert_allclose(R.rot6d_to_matrix(noisy), m, atol=1e-12)


@pytest.mark.parametrize("angle", [np.pi, np.pi - 1e-7, np.pi - 1e-3, 1e-9, 0.0])
def test_round_trips_near_pi_and_zero(angle):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    v = axis * angle
    m = R.axis_angle_to_matrix(v)
    back = R.matrix_to_axis_angle(m)
    # at exactly pi, v and -v are the same rotation: compare rotations, not vectors
    assert R.rotation_angle_between(R.axis_angle_to_matrix(back), m) < 1e-7
    assert abs(np.linalg.norm(back) - angle) < 1e-7
    m2 = R.rot6d_to_matrix(R.axis_angle_to_rot6d(v))
    np.testing.assert_allclose(m2, m, atol=1e-12)
    q = R.matrix_to_quat(m)
    np.testing.assert_allclose(R.quat_to_matrix(q), m, atol=1e-12)


def test_quat_round_trip_with_sign_ambiguity():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = R.rot6d_to_quat(R.quat_to_rot6d(q))
    # q and -q are one rotation
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)


def test_batch_shapes_are_kept():
    v = np.random.default_rng(4).normal(size=(2, 5, 3))
    assert R.axis_angle_to_rot6d(v).shape == (2, 5, 6)
    assert R.rot6d_to_matrix(R.axis_angle_to_rot6d(v)).shape == (2, 5, 3, 3)
    np.testing.assert_allclose(R.rot6d_to_axis_angle(R.axis_angle_to_rot6d(v)),
                               R.matrix_to_axis_angle(R.axis_angle_to_matrix(v)), atol=1e-12)


def test_bad_input_raises_with_a_clear_message():
    with pytest.raises(ValueError, match="last dimension of 6"):
        R.rot6d_to_matrix(np.zeros(5))
    with pytest.raises(ValueError, match="parallel"):
        R.rot6d_to_matrix(np.array([1.0, 0, 0, 2.0, 0, 0]))
    with pytest.raises(ValueError, match="zero"):
        R.rot6d_to_matrix(np.zeros(6))
    with pytest.raises(ValueError, match="zero norm"):
        R.quat_to_matrix(np.zeros(4))
    with pytest.raises(ValueError, match="NaN"):
        R.axis_angle_to_matrix(np.array([np.nan, 0, 0]))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        R.matrix_to_rot6d(np.zeros((3, 4)))
