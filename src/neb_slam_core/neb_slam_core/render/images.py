"""Whole images rendered from the map: every pixel of a camera at a pose."""

from __future__ import annotations

import numpy as np
import torch

from ..config import RenderConfig
from ..scene.block_map import BlockMap
from ..types import RgbdFrame
from .rays import all_pixels
from .renderer import render_rays


@torch.no_grad()
def render_depth_image(
    block_map: BlockMap, frame: RgbdFrame, T_world_cam: np.ndarray, render_cfg: RenderConfig, chunk: int = 8192
) -> tuple[np.ndarray, np.ndarray]:
    """Render the full depth ``(H, W)`` and colour ``(H, W, 3)`` images of ``frame``'s camera at a pose.

    Uses deterministic samples (bin centres) and the measured depth for the surface samples, as
    evaluation renders do in neural RGB-D SLAM. Pixels with no sample inside a block render depth 0.
    """
    dev = block_map.device
    px = all_pixels(frame, device=dev)
    rays = px.to_world(torch.as_tensor(T_world_cam, dtype=torch.float32, device=dev))
    ids = block_map.blocks_in_frustum(
        T_world_cam, frame.intrinsics, render_cfg.sampling.near_m, render_cfg.sampling.far_m
    )
    depth, rgb = [], []
    for s in range(0, len(rays), chunk):
        out = render_rays(block_map, rays[s : s + chunk], render_cfg, ids, stratified=False)
        depth.append(torch.where(out.ray_valid, out.depth_m, torch.zeros_like(out.depth_m)))
        rgb.append(out.rgb)
    h, w = frame.depth_m.shape
    return torch.cat(depth).reshape(h, w).cpu().numpy(), torch.cat(rgb).reshape(h, w, 3).cpu().numpy()
