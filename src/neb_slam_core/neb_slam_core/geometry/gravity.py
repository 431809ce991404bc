"""Gravity and the level frame it defines.

The engine's world frame is the first camera's (or the first ground-truth pose's) frame: its axes follow
that camera, so its z axis points wherever the camera looked. A robot's ``map`` frame has z up (REP-103).
:func:`level_frame` builds that frame from the direction of gravity, a forward direction and an origin;
:func:`floor_down` measures the direction of gravity from one depth image, as the normal of the floor
(the largest roughly horizontal plane below the camera).
"""

from __future__ import annotations

import numpy as np

from neb_slam_core.geometry.rays import backproject_depth
from neb_slam_core.types import Intrinsics


def level_frame(down: np.ndarray, forward: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``T_level_world`` (4x4) of the frame with z against ``down``, x along ``forward`` projected onto the
    horizontal plane, y = z x x (x forward, y left, z up: REP-103), origin at ``origin``; all three given
    in world coordinates. A ``forward`` along gravity leaves the yaw undefined: then world x (or y)
    projected is used."""
    z = -np.asarray(down, dtype=np.float64)
    z = z / np.linalg.norm(z)
    for f in (np.asarray(forward, dtype=np.float64), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        x = f - (f @ z) * z
        if np.linalg.norm(x) > 1e-6 * max(np.linalg.norm(f), 1.0):
            break
    x = x / np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: the level axes in world coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.asarray(origin, dtype=np.float64)
    return T


def floor_down(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    up_prior: np.ndarray,
    max_tilt_deg: float = 45.0,
    inlier_m: float = 0.02,
    min_height_m: float = 0.1,
    min_fraction: float = 0.05,
    n_points: int = 5000,
    iterations: int = 400,
    seed: int = 0,
) -> np.ndarray | None:
    """Direction of gravity (unit vector, camera frame) from the floor in ``depth_m``, or None when no
    floor is seen.

    RANSAC over ``n_points`` valid pixels: a candidate plane counts when its normal is within
    ``max_tilt_deg`` of ``up_prior`` (camera frame: roughly up, e.g. from the mounting) and the camera is
    at least ``min_height_m`` above it; the plane with most points within ``inlier_m`` wins, and needs
    ``min_fraction`` of the points. Its inliers are fitted again by least squares (the smallest singular
    vector of the centred points). A table top passes as well as the floor: both are level.
    """
    pts = backproject_depth(np.asarray(depth_m), intrinsics)
    if len(pts) < 3:
        return None
    rng = np.random.default_rng(seed)
    pts = pts[rng.choice(len(pts), size=min(n_points, len(pts)), replace=False)]
    up = np.asarray(up_prior, dtype=np.float64)
    up = up / np.linalg.norm(up)
    cos_tilt = np.cos(np.deg2rad(max_tilt_deg))
    best, best_count = None, 0
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), size=3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n = n / norm
        if n @ up < 0:
            n = -n
        if n @ up < cos_tilt or -(n @ a) < min_height_m:  # too steep, or not below the camera
            continue
        count = int(np.count_nonzero(np.abs((pts - a) @ n) < inlier_m))
        if count > best_count:
            best, best_count = (n, a), count
    if best is None or best_count < min_fraction * len(pts):
        return None
    n, a = best
    inliers = pts[np.abs((pts - a) @ n) < inlier_m]
    centred = inliers - inliers.mean(axis=0)
    n_fit = np.linalg.svd(centred, full_matrices=False)[2][-1]
    if n_fit @ up < 0:
        n_fit = -n_fit
    return -n_fit
