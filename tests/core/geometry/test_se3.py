"""SE(3) helpers."""

import numpy as np
from scipy.spatial.transform import Rotation

from neb_slam_core.geometry.se3 import interpolate_correction, make_pose


def pose(rotvec_deg, t) -> np.ndarray:
    return make_pose(Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix(), np.asarray(t, dtype=np.float64))


def test_interpolated_correction_ends():
    delta = pose([10.0, 20.0, -5.0], [0.3, -0.2, 0.1])
    pivot = np.array([1.0, 2.0, 3.0])
    assert np.allclose(interpolate_correction(delta, pivot, 1.0), delta)
    assert np.allclose(interpolate_correction(delta, pivot, 0.0), np.eye(4))
    half = interpolate_correction(delta, pivot, 0.5)
    # half the rotation angle, half the pivot's displacement
    assert np.isclose(
        Rotation.from_matrix(half[:3, :3]).magnitude(), 0.5 * Rotation.from_matrix(delta[:3, :3]).magnitude()
    )
    assert np.allclose(half[:3, :3] @ pivot + half[:3, 3] - pivot, 0.5 * (delta[:3, :3] @ pivot + delta[:3, 3] - pivot))
