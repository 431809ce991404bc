"""Ray batches: the pixels an optimisation step renders, with their observations."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..geometry.rays import pixel_directions, rays_world
from ..types import RgbdFrame


@dataclass
class RayBatch:
    """``R`` rays in the world frame with what the camera observed along them.

    Attributes:
        origins: ``(R, 3)`` ray origins (camera centres).
        dirs: ``(R, 3)`` directions whose camera-frame z is 1 (ray parameter = z-depth).
        rgb: ``(R, 3)`` observed colour in [0, 1].
        depth_m: ``(R,)`` observed depth, 0 where invalid.
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    rgb: torch.Tensor
    depth_m: torch.Tensor

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, index) -> RayBatch:
        """The rays selected by ``index`` (a slice, an index tensor or a mask)."""
        return RayBatch(self.origins[index], self.dirs[index], self.rgb[index], self.depth_m[index])

    @staticmethod
    def cat(batches: list[RayBatch]) -> RayBatch:
        return RayBatch(*(torch.cat([getattr(b, f) for b in batches]) for f in ("origins", "dirs", "rgb", "depth_m")))


@dataclass
class PixelSamples:
    """Pixels drawn from one frame, in the camera frame (so the pose can change afterwards).

    Attributes:
        dirs_cam: ``(R, 3)`` camera-frame directions (z = 1).
        rgb: ``(R, 3)`` colour in [0, 1].
        depth_m: ``(R,)`` depth, 0 invalid.
        uv: ``(R, 2)`` integer pixel coordinates.
    """

    dirs_cam: torch.Tensor
    rgb: torch.Tensor
    depth_m: torch.Tensor
    uv: torch.Tensor

    def to_world(self, T_world_cam: torch.Tensor) -> RayBatch:
        """Rays for pose ``T_world_cam`` (4, 4), differentiable in the pose."""
        origins, dirs = rays_world(T_world_cam, self.dirs_cam.to(T_world_cam.dtype))
        return RayBatch(origins, dirs, self.rgb, self.depth_m)

    def __len__(self) -> int:
        return self.dirs_cam.shape[0]


def sample_pixels(
    frame: RgbdFrame,
    n: int,
    generator: np.random.Generator,
    valid_depth_only: bool = False,
    border: int = 0,
    device: torch.device | str = "cpu",
) -> PixelSamples:
    """Draw ``n`` random pixels (without replacement when possible) of ``frame``.

    ``valid_depth_only`` restricts the draw to pixels with depth; ``border`` skips that many pixels at
    each image edge.
    """
    h, w = frame.depth_m.shape
    if valid_depth_only:
        mask = frame.depth_m > 0
        if border:
            mask[:border] = mask[-border:] = False
            mask[:, :border] = mask[:, -border:] = False
        flat = np.flatnonzero(mask)
    else:
        vv, uu = np.mgrid[border : h - border, border : w - border]
        flat = (vv * w + uu).ravel()
    if flat.size == 0:
        return all_pixels(frame, np.zeros(0, dtype=np.int64), device)
    pick = generator.choice(flat, size=n, replace=flat.size < n)
    return all_pixels(frame, pick, device)


def all_pixels(
    frame: RgbdFrame, flat_index: np.ndarray | None = None, device: torch.device | str = "cpu"
) -> PixelSamples:
    """The pixels ``flat_index`` (row-major) of ``frame``, or every pixel when None."""
    h, w = frame.depth_m.shape
    if flat_index is None:
        flat_index = np.arange(h * w)
    v, u = np.divmod(flat_index, w)
    u_t = torch.as_tensor(u, device=device)
    v_t = torch.as_tensor(v, device=device)
    rgb = torch.as_tensor(frame.rgb.reshape(-1, 3)[flat_index], device=device).float() / 255.0
    depth = torch.as_tensor(frame.depth_m.reshape(-1)[flat_index], device=device).float()
    return PixelSamples(pixel_directions(frame.intrinsics, u_t, v_t), rgb, depth, torch.stack([u_t, v_t], dim=1))
