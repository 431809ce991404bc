"""Ray-cast RGB-D rendering of a textured synthetic mesh.

Camera model: a pinhole without distortion. **Pixel convention**: integer pixel coordinates ``(u, v)``
are pixel *centres*; the image covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``; the ray of pixel
``(u, v)`` is ``K^-1 [u, v, 1]`` in the camera frame (OpenCV axes: x right, y down, z forward), which is
the rule the rest of the project back-projects with (``x = depth * K^-1 [u, v, 1]``). A centred
principal point is therefore ``((W - 1) / 2, (H - 1) / 2)``.

Depth is the z coordinate of the hit point in the camera frame (distance along the optical axis, not
along the ray), kept when it lies in ``[min_depth_m, max_depth_m]``, else 0; rays that hit nothing read
0. Depth always comes from the ray through the pixel centre. Colour is the procedural albedo at the hit
point times Lambertian shading from a fixed light direction, ``albedo * (ambient + (1 - ambient) *
max(0, n . l))`` with ``n`` the surface normal facing the camera; with ``supersample = s > 1`` it is the
mean over an ``s x s`` grid of rays inside the pixel (anti-aliasing of the textures).

Ray casting uses Embree through trimesh (``trimesh.ray.ray_pyembree``, package ``embreex``); when that
cannot be imported the pure-Python trimesh intersector is used (much slower) after one warning. Embree
works in float32, so only the hit triangle is taken from it; the hit point is recomputed in float64
from the triangle's plane.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from ..errors import ConfigError
from ..types import Intrinsics
from .textures import Material, albedo, surface_uv

log = logging.getLogger(__name__)

#: direction towards the light in the z-up world (unit length after normalisation)
DEFAULT_LIGHT_DIR = (0.35, 0.55, 0.76)
DEFAULT_AMBIENT = 0.45

_warned_fallback = False


@dataclass(frozen=True)
class CameraSpec:
    """The synthetic camera.

    Attributes:
        width, height: image size in pixels.
        fov_h_deg: horizontal field of view over the full image width (W pixels); square pixels.
        min_depth_m, max_depth_m: valid depth range; outside it depth reads 0.
        supersample: colour rays per pixel along each axis (1 = one ray through the centre).
    """

    width: int = 160
    height: int = 120
    fov_h_deg: float = 65.0
    min_depth_m: float = 0.1
    max_depth_m: float = 10.0
    supersample: int = 2

    def validate(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"CameraSpec: image must be at least 8x8 pixels, got {self.width}x{self.height}")
        if not 10.0 <= self.fov_h_deg <= 150.0:
            raise ConfigError(f"CameraSpec.fov_h_deg: expected 10..150 degrees, got {self.fov_h_deg}")
        if not 0.0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError(
                f"CameraSpec: expected 0 < min_depth_m < max_depth_m, got {self.min_depth_m}, {self.max_depth_m}"
            )
        if self.max_depth_m > 13.0:
            raise ConfigError("CameraSpec.max_depth_m: 16-bit depth PNGs at 5000 per metre hold at most 13.1 m")
        if not 1 <= self.supersample <= 4:
            raise ConfigError(f"CameraSpec.supersample: expected 1..4, got {self.supersample}")

    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics with the principal point at the image centre (pixel-centre convention)."""
        self.validate()
        fx = 0.5 * self.width / math.tan(math.radians(self.fov_h_deg) / 2.0)
        return Intrinsics(fx, fx, 0.5 * (self.width - 1), 0.5 * (self.height - 1), self.width, self.height)


@dataclass
class RenderedView:
    """One rendered view.

    Attributes:
        rgb: ``(H, W, 3)`` uint8 RGB.
        depth_m: ``(H, W)`` float32 z-depth in metres, 0 = no measurement.
        cos_incidence: ``(H, W)`` float32 |cos| of the angle between the centre ray and the surface normal (0: no hit).
        face_index: ``(H, W)`` int64 hit triangle of the centre ray, -1 where none.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    cos_incidence: np.ndarray
    face_index: np.ndarray


def pixel_rays(intrinsics: Intrinsics, offset_u: float = 0.0, offset_v: float = 0.0) -> np.ndarray:
    """Camera-frame rays ``K^-1 [u + offset_u, v + offset_v, 1]`` of every pixel, row-major -> ``(H*W, 3)``
    float64 with z = 1 (so the ray parameter of a hit is its z-depth)."""
    k = intrinsics
    u, v = np.meshgrid(
        np.arange(k.width, dtype=np.float64) + offset_u, np.arange(k.height, dtype=np.float64) + offset_v
    )
    return np.stack([(u.ravel() - k.cx) / k.fx, (v.ravel() - k.cy) / k.fy, np.ones(u.size)], axis=1)


def make_intersector(mesh: trimesh.Trimesh):
    """(intersector, backend name): Embree when importable, else trimesh's own, with one warning."""
    global _warned_fallback
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh), "embree"
    except ImportError as exc:
        if not _warned_fallback:
            log.warning(
                "Embree ray casting unavailable (%s); falling back to trimesh's pure-Python intersector, "
                "which is much slower (pip install embreex)",
                exc,
            )
            _warned_fallback = True
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh), "trimesh"


class Renderer:
    """Renders colour and depth of a textured mesh from camera poses.

    Args:
        mesh: the scene, ``(F, 3)`` faces.
        face_material: ``(F,)`` index into ``materials`` per face.
        materials: the procedural materials.
        intrinsics: the pinhole camera (pixel-centre convention, see the module docstring).
        min_depth_m, max_depth_m: valid depth range.
        supersample: colour rays per pixel along each axis.
        light_dir: direction towards the light in the world frame.
        ambient: the share of light that does not depend on the normal.
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        face_material: np.ndarray,
        materials: Sequence[Material],
        intrinsics: Intrinsics,
        *,
        min_depth_m: float = 0.1,
        max_depth_m: float = 10.0,
        supersample: int = 1,
        light_dir: Sequence[float] = DEFAULT_LIGHT_DIR,
        ambient: float = DEFAULT_AMBIENT,
    ):
        face_material = np.asarray(face_material)
        if face_material.shape != (len(mesh.faces),):
            raise ValueError(f"Renderer: face_material has shape {face_material.shape}, expected ({len(mesh.faces)},)")
        self.mesh = mesh
        self.face_material = face_material.astype(np.int64)
        self.materials = list(materials)
        self.intrinsics = intrinsics
        self.min_depth_m, self.max_depth_m = float(min_depth_m), float(max_depth_m)
        self.supersample = int(supersample)
        light = np.asarray(light_dir, dtype=np.float64)
        self.light_dir = light / np.linalg.norm(light)
        self.ambient = float(ambient)
        self._intersector, self.backend = make_intersector(mesh)
        self._normals = np.asarray(mesh.face_normals, dtype=np.float64)
        self._plane_d = np.einsum("ij,ij->i", self._normals, np.asarray(mesh.triangles[:, 0, :], dtype=np.float64))
        # Lambertian factor of each face seen from its front (normal side) and from its back
        n_dot_l = self._normals @ self.light_dir
        self._light = np.stack(
            [
                self.ambient + (1.0 - self.ambient) * np.maximum(n_dot_l, 0.0),
                self.ambient + (1.0 - self.ambient) * np.maximum(-n_dot_l, 0.0),
            ],
            axis=1,
        )
        s = self.supersample
        offsets = [(i + 0.5) / s - 0.5 for i in range(s)] if s > 1 else []
        # ray bundle: pixel centres first (depth), then the s x s colour samples of every pixel
        self._n_pixels = intrinsics.width * intrinsics.height
        self._rays_cam = np.concatenate(
            [pixel_rays(intrinsics)] + [pixel_rays(intrinsics, ou, ov) for ov in offsets for ou in offsets]
        )

    @classmethod
    def for_scene(cls, scene, intrinsics: Intrinsics | None = None, **kwargs) -> Renderer:
        """A renderer of a :class:`~neb_slam_core.synth.scene.SyntheticScene` with its camera spec."""
        cam = scene.spec.camera
        kwargs.setdefault("supersample", cam.supersample)
        kwargs.setdefault("min_depth_m", cam.min_depth_m)
        kwargs.setdefault("max_depth_m", cam.max_depth_m)
        return cls(scene.mesh, scene.face_material, scene.materials, intrinsics or cam.intrinsics(), **kwargs)

    def cast(
        self, T_world_cam: np.ndarray, rays_cam: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cast camera-frame rays ``(N, 3)`` (z = 1) from pose ``T_world_cam``.

        Returns the hit triangle ``(N,)`` (-1: none), the z-depth ``(N,)`` (0 where none), the world hit
        points ``(N, 3)`` and the world ray directions ``(N, 3)``.
        """
        T = np.asarray(T_world_cam, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        dirs = rays_cam @ np.ascontiguousarray(R.T)
        tri = np.asarray(self._intersector.intersects_first(np.broadcast_to(t, dirs.shape), dirs), dtype=np.int64)
        z = np.zeros(len(dirs))
        hit = np.flatnonzero(tri >= 0)
        n = self._normals[tri[hit]]
        denom = np.einsum("ij,ij->i", n, dirs[hit])
        with np.errstate(divide="ignore", invalid="ignore"):
            zh = (self._plane_d[tri[hit]] - n @ t) / denom
        bad = ~(np.isfinite(zh) & (zh > 0))
        zh[bad] = 0.0
        tri[hit[bad]] = -1
        z[hit] = zh
        return tri, z, t + dirs * z[:, None], dirs

    def shade(self, tri: np.ndarray, points: np.ndarray, dirs_world: np.ndarray) -> np.ndarray:
        """Shaded colour ``(N, 3)`` float in [0, 1] of hits on triangles ``tri`` at ``points`` seen along
        ``dirs_world``; black where ``tri < 0``."""
        out = np.zeros((len(tri), 3))
        hit = np.flatnonzero(tri >= 0)
        if len(hit) == 0:
            return out
        th = tri[hit]
        n = self._normals[th]
        back = (np.einsum("ij,ij->i", n, dirs_world[hit]) > 0).astype(np.int64)
        light = self._light[th, back]
        uv = surface_uv(points[hit], n)
        mat = self.face_material[th]
        order = np.argsort(mat, kind="stable")
        mat_sorted = mat[order]
        cuts = np.flatnonzero(np.diff(mat_sorted)) + 1
        col = np.empty((len(hit), 3))
        for group in np.split(order, cuts):
            col[group] = albedo(self.materials[mat[group[0]]], uv[group])
        out[hit] = col * light[:, None]
        return out

    def render(self, T_world_cam: np.ndarray) -> RenderedView:
        """Render the view from ``T_world_cam`` ``(4, 4)`` (camera-to-world, OpenCV axes)."""
        k = self.intrinsics
        n_px = self._n_pixels
        tri_all, z_all, points, dirs = self.cast(T_world_cam, self._rays_cam)
        if self.supersample > 1:
            col = self.shade(tri_all[n_px:], points[n_px:], dirs[n_px:])
            color = col.reshape(-1, n_px, 3).mean(axis=0)
        else:
            color = self.shade(tri_all, points, dirs)
        tri, z = tri_all[:n_px], z_all[:n_px]
        depth = np.where((z >= self.min_depth_m) & (z <= self.max_depth_m), z, 0.0)
        cos_inc = np.zeros(n_px)
        hit = tri >= 0
        d = dirs[:n_px][hit]
        cos_inc[hit] = np.abs(np.einsum("ij,ij->i", self._normals[tri[hit]], d)) / np.linalg.norm(d, axis=1)
        rgb = np.clip(np.round(color * 255.0), 0, 255).astype(np.uint8)
        return RenderedView(
            rgb.reshape(k.height, k.width, 3),
            depth.astype(np.float32).reshape(k.height, k.width),
            cos_inc.astype(np.float32).reshape(k.height, k.width),
            tri.reshape(k.height, k.width),
        )
