"""Back-projection of depth pixels, by hand, and the bounds of a depth image's points against them."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from neb_slam_core.geometry.rays import backproject_depth, backproject_pixels, depth_bounds
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.types import Intrinsics

K = Intrinsics(fx=2.0, fy=4.0, cx=1.0, cy=1.0, width=4, height=3)


def test_a_pixel_by_hand():
    # u = 3, v = 2 at 2 m: x = (3 - 1) / 2 * 2 = 2, y = (2 - 1) / 4 * 2 = 0.5
    np.testing.assert_allclose(backproject_pixels(np.array([3]), np.array([2]), np.array([2.0]), K), [[2.0, 0.5, 2.0]])
    T = make_pose(np.diag([1.0, -1.0, -1.0]), [10.0, 0.0, 1.0])
    np.testing.assert_allclose(
        backproject_pixels(np.array([3]), np.array([2]), np.array([2.0]), K, T), [[12.0, -0.5, -1.0]]
    )


def test_the_depth_image_is_its_valid_pixels_back_projected():
    depth = np.zeros((3, 4), np.float32)
    depth[0, 1], depth[2, 3], depth[1, 0] = 1.0, 2.0, 0.5
    v, u = np.nonzero(depth > 0)
    T = make_pose(np.eye(3), [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(backproject_depth(depth, K, T), backproject_pixels(u, v, depth[v, u], K, T))
    assert backproject_depth(depth, K).shape == (3, 3)


def test_depth_bounds_are_the_box_of_the_back_projected_points():
    """The per-axis pass gives the box of backproject_depth's points (the reference), for a rotated camera
    and an image with invalid pixels; None without any depth."""
    rng = np.random.default_rng(3)
    k = Intrinsics(fx=50.0, fy=55.0, cx=31.5, cy=23.5, width=64, height=48)
    depth = rng.uniform(0.3, 4.0, (48, 64)).astype(np.float32)
    depth[rng.random((48, 64)) < 0.3] = 0.0
    T = make_pose(Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix(), [1.0, -2.0, 0.5])
    pts = backproject_depth(depth, k, T)
    lo, hi = depth_bounds(depth, k, T)
    np.testing.assert_allclose(lo, pts.min(axis=0), atol=1e-9)
    np.testing.assert_allclose(hi, pts.max(axis=0), atol=1e-9)
    assert depth_bounds(np.zeros((48, 64), np.float32), k, T) is None
