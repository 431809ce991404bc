"""SE(3) helpers on 4x4 float64 numpy matrices.

Quaternions follow the TUM / ROS convention: Hamilton, ``(qx, qy, qz, qw)`` with w last.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# OpenGL camera axes (x right, y up, z backward) -> OpenCV optical axes (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 transform with rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform ``(..., 4, 4)`` without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def skew(v: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` cross-product matrices of ``(..., 3)`` vectors: ``skew(a) @ b = a x b``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_left_jacobian(omega: np.ndarray) -> np.ndarray:
    """``(3, 3)`` left Jacobian of SO(3) at the rotation vector ``omega``: ``exp(omega + d) = exp(J d) exp(omega)``
    to first order in ``d``; ``J = I + (1 - cos t) / t^2 W + (t - sin t) / t^3 W^2`` with ``W = skew(omega)``,
    ``t = |omega|`` (its series below 1e-4 rad, where the closed form loses digits)."""
    omega = np.asarray(omega, dtype=np.float64)
    t = float(np.linalg.norm(omega))
    W = skew(omega)
    if t < 1e-4:
        a, b = 0.5 - t * t / 24.0, 1.0 / 6.0 - t * t / 120.0
    else:
        a, b = (1.0 - np.cos(t)) / t**2, (t - np.sin(t)) / t**3
    return np.eye(3) + a * W + b * (W @ W)


def interpolate_correction(delta: np.ndarray, pivot: np.ndarray, w) -> np.ndarray:
    """The share ``w`` in [0, 1] of the rigid correction ``delta`` (4x4): rotation ``exp(w log R)``
    about ``pivot`` (3,) plus ``w`` times the displacement of ``pivot``. ``w = 1`` gives ``delta``.
    Batched over leading axes: ``delta`` (..., 4, 4), ``pivot`` (..., 3) and ``w`` (...) broadcast."""
    delta, pivot, w = (
        np.asarray(delta, dtype=np.float64),
        np.asarray(pivot, dtype=np.float64),
        np.asarray(w, dtype=np.float64),
    )
    shape = np.broadcast_shapes(delta.shape[:-2], pivot.shape[:-1], w.shape)
    delta = np.broadcast_to(delta, shape + (4, 4)).reshape(-1, 4, 4)
    pivot = np.broadcast_to(pivot, shape + (3,)).reshape(-1, 3)
    w = np.broadcast_to(w, shape).reshape(-1)
    R_w = Rotation.from_rotvec(w[:, None] * Rotation.from_matrix(delta[:, :3, :3]).as_rotvec()).as_matrix()
    displacement = (delta[:, :3, :3] @ pivot[:, :, None])[..., 0] + delta[:, :3, 3] - pivot
    out = np.zeros((len(w), 4, 4))
    out[:, :3, :3] = R_w
    out[:, :3, 3] = pivot - (R_w @ pivot[:, :, None])[..., 0] + w[:, None] * displacement
    out[:, 3, 3] = 1.0
    return out.reshape(shape + (4, 4))


def pose_from_tum(txyz_qxyzw: np.ndarray) -> np.ndarray:
    """``(..., 7)`` rows ``tx ty tz qx qy qz qw`` -> ``(..., 4, 4)`` poses."""
    v = np.asarray(txyz_qxyzw, dtype=np.float64)
    flat = v.reshape(-1, 7)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(flat[:, 3:]).as_matrix()
    T[:, :3, 3] = flat[:, :3]
    return T.reshape(v.shape[:-1] + (4, 4))


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` poses -> ``(..., 7)`` rows ``tx ty tz qx qy qz qw`` (qw >= 0)."""
    T = np.asarray(T, dtype=np.float64)
    flat = T.reshape(-1, 4, 4)
    q = Rotation.from_matrix(flat[:, :3, :3]).as_quat()
    q[q[:, 3] < 0] *= -1.0
    out = np.concatenate([flat[:, :3, 3], q], axis=1)
    return out.reshape(T.shape[:-2] + (7,))


def rotation_error(R: np.ndarray) -> float:
    """How far ``R`` (3, 3) is from a proper rotation: max |R^T R - I| and |det R - 1|."""
    return float(max(np.abs(R.T @ R - np.eye(3)).max(), abs(np.linalg.det(R) - 1.0)))


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """True when ``T`` is a finite 4x4 rigid transform (rotation within ``tol``, last row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        return False
    return rotation_error(T[:3, :3]) <= tol


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation part of nearly rigid ``T`` (``(..., 4, 4)``) onto SO(3) (SVD), keep the
    translation."""
    T = np.asarray(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, -1] *= -1
    out = np.zeros(T.shape)
    out[..., :3, :3] = U @ Vt
    out[..., :3, 3] = T[..., :3, 3]
    out[..., 3, 3] = 1.0
    return out


def rigidity_error(T: np.ndarray) -> float:
    """How far ``T`` (``(..., 4, 4)``) is from rigid motions: the largest entry of ``R R^T - I`` or of
    the last row's difference from ``(0, 0, 0, 1)``; infinite when an entry is not finite."""
    T = np.asarray(T, dtype=np.float64)
    if not np.all(np.isfinite(T)):
        return float("inf")
    R = T[..., :3, :3]
    gram = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(initial=0.0)
    row = np.abs(T[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0)
    return float(max(gram, row, 0.0 if np.all(np.linalg.det(R) > 0) else float("inf")))
