"""Rotation representations used by the absolute action convention (paper Sec. 4.1).

Quaternions are (x, y, z, w) like robosuite. Quaternion / matrix / axis-angle conversions are delegated to
``scipy.spatial.transform.Rotation`` (stable near angle pi, batched); the 6-D representation (Zhou et al.,
"On the Continuity of Rotation Representations in Neural Networks", CVPR 2019) is ours: the first two columns
of the rotation matrix, mapped back with Gram-Schmidt. Every function accepts a leading batch shape.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

_EPS = 1e-9


def _check_last(x: np.ndarray, size: int, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0 or x.shape[-1] != size:
        raise ValueError(f"{name} must have a last dimension of {size}, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf; pass finite values")
    return x


def _check_matrix(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {m.shape}")
    return m


def _batched(fn, x: np.ndarray, item_ndim: int) -> np.ndarray:
    """Apply a scipy function that expects (N, ...) to an array with any leading batch shape."""
    lead = x.shape[: x.ndim - item_ndim]
    out = fn(x.reshape((-1,) + x.shape[x.ndim - item_ndim:]))
    return out.reshape(lead + out.shape[1:])


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternion(s) -> rotation matrix(es); the quaternion need not be normalised."""
    q = _check_last(quat, 4, "quaternion")
    if np.any(np.linalg.norm(q, axis=-1) < _EPS):
        raise ValueError("quaternion has zero norm; a rotation quaternion must be non-zero")
    return _batched(lambda a: Rotation.from_quat(a).as_matrix(), q, 1)


def matrix_to_quat(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) -> unit (x, y, z, w) quaternion(s) with w >= 0."""
    m = _check_matrix(matrix)
    return _batched(lambda a: Rotation.from_matrix(a).as_quat(canonical=True), m, 2)


def axis_angle_to_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """Axis-angle (unit axis times angle in radians, as robosuite's OSC input) -> rotation matrix(es)."""
    v = _check_last(axis_angle, 3, "axis-angle")
    return _batched(lambda a: Rotation.from_rotvec(a).as_matrix(), v, 1)


def matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) -> axis-angle with angle in [0, pi]."""
    m = _check_matrix(matrix)
    return _batched(lambda a: Rotation.from_matrix(a).as_rotvec(), m, 2)


def quat_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    return matrix_to_axis_angle(quat_to_matrix(quat))


def axis_angle_to_quat(axis_angle: np.ndarray) -> np.ndarray:
    return matrix_to_quat(axis_angle_to_matrix(axis_angle))


def matrix_to_rot6d(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) -> 6-D representation: first column then second column (Zhou et al. 2019)."""
    m = _check_matrix(matrix)
    return np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)


def rot6d_is_degenerate(rot6d: np.ndarray) -> np.ndarray:
    """Where a 6-D rotation defines no rotation (a zero first column, or columns parallel or the second zero):
    the inputs ``rot6d_to_matrix`` refuses. Boolean, over the leading batch shape."""
    r = _check_last(rot6d, 6, "6-D rotation")
    a1, a2 = r[..., :3], r[..., 3:]
    n1 = np.linalg.norm(a1, axis=-1)
    b1 = a1 / np.maximum(n1, _EPS)[..., None]
    u2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    return (n1 < _EPS) | (np.linalg.norm(u2, axis=-1) < _EPS * np.maximum(1.0, np.linalg.norm(a2, axis=-1)))


def rot6d_to_matrix(rot6d: np.ndarray) -> np.ndarray:
    """6-D representation -> rotation matrix by Gram-Schmidt; any two independent 3-vectors are accepted.

    Raises ValueError when the two vectors are (nearly) parallel or zero, where no rotation is defined.
    """
    r = _check_last(rot6d, 6, "6-D rotation")
    a1, a2 = r[..., :3], r[..., 3:]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    if np.any(n1 < _EPS):
        raise ValueError("6-D rotation: first column is zero; it must be a non-zero 3-vector")
    b1 = a1 / n1
    u2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    n2 = np.linalg.norm(u2, axis=-1, keepdims=True)
    if np.any(n2 < _EPS * np.maximum(1.0, np.linalg.norm(a2, axis=-1, keepdims=True))):
        raise ValueError("6-D rotation: the two columns are parallel or the second is zero; they must span a plane")
    b2 = u2 / n2
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


def axis_angle_to_rot6d(axis_angle: np.ndarray) -> np.ndarray:
    return matrix_to_rot6d(axis_angle_to_matrix(axis_angle))


def rot6d_to_axis_angle(rot6d: np.ndarray) -> np.ndarray:
    return matrix_to_axis_angle(rot6d_to_matrix(rot6d))


def quat_to_rot6d(quat: np.ndarray) -> np.ndarray:
    return matrix_to_rot6d(quat_to_matrix(quat))


def rot6d_to_quat(rot6d: np.ndarray) -> np.ndarray:
    return matrix_to_quat(rot6d_to_matrix(rot6d))


def rotation_angle_between(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Geodesic angle (radians) between rotation matrices, computed stably via the relative rotation's rotvec."""
    rel = np.swapaxes(_check_matrix(m1), -1, -2) @ _check_matrix(m2)
    return np.linalg.norm(matrix_to_axis_angle(rel), axis=-1)
