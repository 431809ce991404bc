"""Camera rays and back-projection (torch, device-agnostic).

Pixel convention used throughout the project: integer pixel coordinates (u, v) are pixel centres, and the
ray of pixel (u, v) is ``K^-1 [u, v, 1]``; a pixel with depth d back-projects to ``d K^-1 [u, v, 1]`` in the
camera frame. Ray directions keep z = 1 in the camera frame, so the ray parameter equals the z-depth.
"""

from __future__ import annotations

import numpy as np
import torch

from ..types import Intrinsics


def pixel_directions(intrinsics: Intrinsics, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``(N,)`` pixel coordinates -> ``(N, 3)`` camera-frame directions with z = 1."""
    k = intrinsics
    x = (u.to(torch.float32) - k.cx) / k.fx
    y = (v.to(torch.float32) - k.cy) / k.fy
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply ``T`` (4, 4) or ``(N, 4, 4)`` to ``(N, 3)`` points."""
    if T.dim() == 2:
        return points @ T[:3, :3].T + T[:3, 3]
    return (T[:, :3, :3] @ points[..., None])[..., 0] + T[:, :3, 3]


def rays_world(T_world_cam: torch.Tensor, dirs_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World-frame ray origins and directions ``(N, 3)`` each, for one pose (4, 4) or one per ray (N, 4, 4)."""
    if T_world_cam.dim() == 2:
        dirs = dirs_cam @ T_world_cam[:3, :3].T
        origins = T_world_cam[:3, 3].expand_as(dirs)
    else:
        dirs = (T_world_cam[:, :3, :3] @ dirs_cam[..., None])[..., 0]
        origins = T_world_cam[:, :3, 3]
    return origins, dirs


def backproject_depth(
    depth_m: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray | None = None, stride: int = 1
) -> np.ndarray:
    """All valid pixels of a depth image (every ``stride``-th row/column) -> ``(K, 3)`` points
    (world frame when ``T_world_cam`` is given, camera frame otherwise), float64."""
    d = depth_m[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    return backproject_pixels(u * stride, v * stride, d[v, u], intrinsics, T_world_cam)


def depth_bounds(
    depth_m: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The world-axis-aligned bounds ``(lo, hi)`` of the back-projected valid pixels of a depth image, the
    box of :func:`backproject_depth`'s points, without building them: world coordinate ``i`` of pixel
    ``(u, v)`` is ``t_i + d(u, v) (R_i0 x_u + R_i1 y_v + R_i2)`` with ``x_u = (u - cx) / fx`` and
    ``y_v = (v - cy) / fy``, a per-column and a per-row term, so each axis is one pass over the image.
    None when no pixel has depth."""
    d = np.asarray(depth_m, dtype=np.float64)
    valid = d > 0
    if not valid.any():
        return None
    k = intrinsics
    x = (np.arange(d.shape[1]) - k.cx) / k.fx
    y = (np.arange(d.shape[0]) - k.cy) / k.fy
    T = np.asarray(T_world_cam, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    lo, hi = np.empty(3), np.empty(3)
    for i in range(3):
        p = d * (R[i, 0] * x[None, :] + R[i, 1] * y[:, None] + R[i, 2])
        lo[i] = t[i] + np.min(p, where=valid, initial=np.inf)
        hi[i] = t[i] + np.max(p, where=valid, initial=-np.inf)
    return lo, hi


def backproject_pixels(
    u: np.ndarray, v: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray | None = None
) -> np.ndarray:
    """Pixels ``(u, v)`` (integer columns and rows, pixel centres) at depths ``depth_m`` -> ``(K, 3)``
    points (world frame when ``T_world_cam`` is given, camera frame otherwise), float64."""
    z = np.asarray(depth_m, dtype=np.float64)
    k = intrinsics
    pts = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], axis=1)
    if T_world_cam is not None:
        pts = pts @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return pts
