"""The paper's absolute end-effector action convention (Sec. 4.1) and its exact link to robosuite's controller.

Per arm our action is ``[position (3), 6-D rotation (6), gripper (1)]`` (10-D; 20-D for two arms). robosuite's
OSC_POSE controller with ``control_delta=False`` takes ``[position (3), axis-angle (3), gripper (1)]`` per arm
and sets its goal to exactly that pose, so the two are converted without approximation. Pure maths: the
dataset converter that replays delta actions lives in ``convert_abs_actions``.
"""
from __future__ import annotations

import numpy as np

from jepa_envs.tasks import rotations

ABS_DIM_PER_ARM = 10
NATIVE_DIM_PER_ARM = 7


def split_arms(action: np.ndarray, num_arms: int, per_arm: int, name: str) -> np.ndarray:
    """(..., per_arm * num_arms) -> (..., num_arms, per_arm), with an error naming the expected size."""
    action = np.asarray(action, dtype=np.float64)
    if action.shape[-1] != per_arm * num_arms:
        raise ValueError(f"{name} action for {num_arms} arm(s) must have last dimension {per_arm * num_arms}, "
                         f"got shape {action.shape}")
    return action.reshape(action.shape[:-1] + (num_arms, per_arm))


def abs_to_native(action: np.ndarray, num_arms: int) -> np.ndarray:
    """Our absolute action(s) (..., 10 * arms) -> robosuite OSC_POSE absolute input (..., 7 * arms)."""
    a = split_arms(action, num_arms, ABS_DIM_PER_ARM, "absolute")
    out = np.concatenate([a[..., :3], rotations.rot6d_to_axis_angle(a[..., 3:9]), a[..., 9:10]], axis=-1)
    return out.reshape(out.shape[:-2] + (NATIVE_DIM_PER_ARM * num_arms,))


def native_to_abs(action: np.ndarray, num_arms: int) -> np.ndarray:
    """robosuite OSC_POSE absolute input (..., 7 * arms) -> our absolute action(s) (..., 10 * arms)."""
    a = split_arms(action, num_arms, NATIVE_DIM_PER_ARM, "native absolute")
    out = np.concatenate([a[..., :3], rotations.axis_angle_to_rot6d(a[..., 3:6]), a[..., 6:7]], axis=-1)
    return out.reshape(out.shape[:-2] + (ABS_DIM_PER_ARM * num_arms,))


def pose_to_abs(positions: np.ndarray, matrices: np.ndarray, grippers: np.ndarray) -> np.ndarray:
    """Per-arm positions (n, 3), rotation matrices (n, 3, 3) and gripper commands (n,) -> one action (10 n,)."""
    parts = [np.concatenate([p, rotations.matrix_to_rot6d(m), [g]])
             for p, m, g in zip(np.asarray(positions), np.asarray(matrices), np.asarray(grippers))]
    return np.concatenate(parts)
