"""Rigid transforms (4x4, float64) and named quaternion conversions.

Quaternion order is always in the function name: ``xyzw`` is scalar-last (SciPy, ROS, TUM),
``wxyz`` is scalar-first (Eigen, many graphics APIs). SciPy's ``Rotation`` does the conversions:
it is well tested and handles the sign and normalisation corner cases.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "check_rigid",
    "invert_rigid",
    "project_to_rotation",
    "quat_wxyz_from_rotation",
    "quat_xyzw_from_rotation",
    "rotation_angle_deg",
    "rotation_from_quat_wxyz",
    "rotation_from_quat_xyzw",
]


def quat_xyzw_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with w >= 0 from a 3x3 rotation (or [..., 3, 3])."""
    q = Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_quat()
    return np.where(q[..., 3:4] < 0, -q, q)


def quat_wxyz_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 from a 3x3 rotation (or [..., 3, 3])."""
    q = quat_xyzw_from_rotation(rotation)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def rotation_from_quat_xyzw(quat: np.ndarray) -> np.ndarray:
    """3x3 rotation from a (not necessarily unit) quaternion in (x, y, z, w) order."""
    return Rotation.from_quat(np.asarray(quat, dtype=np.float64)).as_matrix()


def rotation_from_quat_wxyz(quat: np.ndarray) -> np.ndarray:
    """3x3 rotation from a (not necessarily unit) quaternion in (w, x, y, z) order."""
    q = np.asarray(quat, dtype=np.float64)
    return rotation_from_quat_xyzw(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (or a stack [..., 4, 4]) without a general inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def project_to_rotation(matrix: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to a 3x3 matrix, det = +1, via SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, in degrees."""
    R = np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_b, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def check_rigid(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True if T is a finite 4x4 rigid transform (orthonormal rotation, det +1, last row 0001)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(R.T @ R, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol * 10
        and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=atol)
    )
