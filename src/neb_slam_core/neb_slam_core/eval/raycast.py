"""Ray casting against a triangle mesh (Embree through trimesh): first-hit distances and depth images.

Embree reports which triangle a ray hits first; the distance along the ray is then recomputed in
float64 from that triangle's plane, so depths do not carry Embree's single-precision rounding.
Depth images follow the project's convention: ``(H, W)`` float32 z-depth in metres along the optical
axis (OpenCV axes), 0 where the ray hits nothing.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh

from ..types import Intrinsics

log = logging.getLogger(__name__)

#: rays cast per Embree call when rendering (about 100 MB of temporaries)
MAX_RAYS_PER_CALL = 1 << 19


def _intersector(mesh: trimesh.Trimesh):
    """Embree intersector for ``mesh``; falls back (slowly) to trimesh's pure-numpy one with a warning."""
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except Exception as exc:  # embreex missing or broken: still correct, only slower
        log.warning("Embree ray casting unavailable (%s); using trimesh's slow ray tracer", exc)
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)


class RayCaster:
    """Casts rays against one mesh.

    Args:
        mesh: the triangle mesh (world coordinates, metres).
    """

    def __init__(self, mesh: trimesh.Trimesh):
        if len(mesh.faces) == 0:
            raise ValueError("RayCaster: the mesh has no faces")
        self.mesh = mesh
        self._rays = _intersector(mesh)
        self._v0 = np.asarray(mesh.vertices, dtype=np.float64)[mesh.faces[:, 0]]
        e1 = np.asarray(mesh.vertices, dtype=np.float64)[mesh.faces[:, 1]] - self._v0
        e2 = np.asarray(mesh.vertices, dtype=np.float64)[mesh.faces[:, 2]] - self._v0
        self._normal = np.cross(e1, e2)  # unnormalised: only ratios are used

    def first_hit_distance(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance along each ray to its first hit.

        Args:
            origins: ``(n, 3)`` ray origins.
            directions: ``(n, 3)`` ray directions (any positive length; normalised here).

        Returns:
            ``(n,)`` float64 distances in metres along the unit direction, ``inf`` where nothing is hit.
        """
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        dist = np.full(len(origins), np.inf)
        if len(origins) == 0:
            return dist
        unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        tri = np.asarray(self._rays.intersects_first(origins, unit))
        hit = np.flatnonzero(tri >= 0)
        if len(hit) == 0:
            return dist
        n = self._normal[tri[hit]]
        denom = (n * unit[hit]).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (n * (self._v0[tri[hit]] - origins[hit])).sum(axis=1) / denom
        bad = ~np.isfinite(t) | (t < 0)
        if bad.any():  # degenerate triangle or grazing ray: take Embree's own hit location
            locs, ray_idx, _ = self._rays.intersects_location(origins[hit[bad]], unit[hit[bad]], multiple_hits=False)
            fixed = np.full(int(bad.sum()), np.inf)
            fixed[ray_idx] = np.linalg.norm(locs - origins[hit[bad]][ray_idx], axis=1)
            t[bad] = fixed
        dist[hit] = t
        return dist

    def render_depth(self, T_world_cams: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """Render z-depth images of the mesh.

        Pixel ``(u, v)`` (column, row) looks through its centre: camera ray ``((u - cx)/fx, (v - cy)/fy, 1)``.

        Args:
            T_world_cams: ``(4, 4)`` or ``(V, 4, 4)`` camera-to-world poses (OpenCV axes).
            intrinsics: the virtual camera.

        Returns:
            ``(H, W)`` or ``(V, H, W)`` float32 depth in metres, 0 where the ray hits nothing.
        """
        T = np.asarray(T_world_cams, dtype=np.float64)
        single = T.ndim == 2
        T = T.reshape(-1, 4, 4)
        dirs_cam = pixel_rays(intrinsics)  # (H*W, 3), z = 1
        inv_len = 1.0 / np.linalg.norm(dirs_cam, axis=1)
        depth = np.zeros((len(T), intrinsics.height * intrinsics.width), np.float32)
        chunk = max(1, MAX_RAYS_PER_CALL // len(dirs_cam))  # views per call: bounds the memory
        for s in range(0, len(T), chunk):
            Tc = T[s : s + chunk]
            dirs_world = (dirs_cam[None] @ np.swapaxes(Tc[:, :3, :3], 1, 2)).reshape(-1, 3)  # rows: R d
            origins = np.repeat(Tc[:, :3, 3], len(dirs_cam), axis=0)
            dist = self.first_hit_distance(origins, dirs_world).reshape(len(Tc), -1)
            # z-depth = distance along the unit ray times its cosine to the optical axis (1 / |d_cam|)
            z = dist * inv_len[None, :]
            depth[s : s + chunk] = np.where(np.isfinite(z), z, 0.0)
        depth = depth.reshape(len(T), intrinsics.height, intrinsics.width)
        return depth[0] if single else depth


def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """``(H*W, 3)`` camera-frame rays through the pixel centres, row-major, with z = 1."""
    u, v = np.meshgrid(np.arange(intrinsics.width, dtype=np.float64), np.arange(intrinsics.height, dtype=np.float64))
    x = (u.ravel() - intrinsics.cx) / intrinsics.fx
    y = (v.ravel() - intrinsics.cy) / intrinsics.fy
    return np.stack([x, y, np.ones_like(x)], axis=1)
