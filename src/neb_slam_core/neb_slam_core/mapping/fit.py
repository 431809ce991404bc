"""Fit the map alone to frames with known poses (mapping with poses fixed).

This is the map-only stage of the paper's optimisation: used to check the representation against
ground truth, to train the map on the first frame, and for the map-only stage after a loop correction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..config import RenderConfig
from ..geometry.rays import backproject_depth
from ..render.rays import RayBatch, all_pixels
from ..render.renderer import objective, render_rays
from ..scene.block_map import BlockMap
from ..types import RgbdFrame
from .optimizer import MapOptimizer


@dataclass(frozen=True)
class FitConfig:
    """Map-only optimisation: ``iterations`` steps of ``rays_per_iteration`` rays drawn from all frames."""

    iterations: int = 300
    rays_per_iteration: int = 2048
    grid_lr: float = 1e-2
    decoder_lr: float = 1e-2


def allocate_blocks(block_map: BlockMap, frames: Sequence[RgbdFrame], poses: Sequence[np.ndarray],
                    near_m: float, far_m: float, rng: np.random.Generator) -> int:
    """Run the allocation rule on each frame in turn (as tracking would); returns the blocks added."""
    before = len(block_map)
    n = block_map.block_cfg.alloc_n_points
    for frame, T in zip(frames, poses):
        pts = backproject_depth(frame.depth_m, frame.intrinsics, T)
        if len(pts) == 0:
            continue
        pts = pts[rng.choice(len(pts), size=min(n, len(pts)), replace=False)]
        ids = block_map.blocks_in_frustum(T, frame.intrinsics, near_m, far_m)
        block_map.allocate_if_needed(torch.as_tensor(pts, dtype=torch.float32, device=block_map.device), ids)
    return len(block_map) - before


class FrameRayPool:
    """Every pixel of a set of posed frames as world-frame rays, to draw random batches from."""

    def __init__(self, frames: Sequence[RgbdFrame], poses: Sequence[np.ndarray], device: torch.device | str = "cpu"):
        batches = []
        for frame, T in zip(frames, poses):
            px = all_pixels(frame, device=device)
            batches.append(px.to_world(torch.as_tensor(T, dtype=torch.float32, device=device)))
        self.rays = RayBatch.cat(batches)

    def draw(self, n: int, generator: torch.Generator) -> RayBatch:
        return self.rays[torch.randint(len(self.rays), (n,), generator=generator, device=self.rays.origins.device)]


def fit_map(block_map: BlockMap, pool: FrameRayPool, render_cfg: RenderConfig, fit_cfg: FitConfig,
            seed: int = 0, progress: bool = False) -> list[float]:
    """Optimise blocks and decoders on random rays of ``pool``; returns the total loss per iteration."""
    g = torch.Generator(device=block_map.device).manual_seed(seed)
    opt = MapOptimizer(block_map, fit_cfg.grid_lr, fit_cfg.decoder_lr)
    steps = range(fit_cfg.iterations)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc="fit map", unit="it")
    history = []
    for _ in steps:
        rays = pool.draw(fit_cfg.rays_per_iteration, g)
        opt.zero_grad()
        loss, _ = objective(block_map, rays, render_cfg, None, generator=g)
        loss.total.backward()
        opt.step()
        history.append(float(loss.total.detach()))
    return history


@torch.no_grad()
def render_depth_image(block_map: BlockMap, frame: RgbdFrame, T_world_cam: np.ndarray, render_cfg: RenderConfig,
                       chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Render the full depth ``(H, W)`` and colour ``(H, W, 3)`` images of ``frame``'s camera at a pose.

    Uses deterministic samples (bin centres) and the measured depth for the surface samples, as
    evaluation renders do in neural RGB-D SLAM.
    """
    dev = block_map.device
    px = all_pixels(frame, device=dev)
    rays = px.to_world(torch.as_tensor(T_world_cam, dtype=torch.float32, device=dev))
    ids = block_map.blocks_in_frustum(T_world_cam, frame.intrinsics, render_cfg.sampling.near_m, render_cfg.sampling.far_m)
    depth, rgb = [], []
    for s in range(0, len(rays), chunk):
        out = render_rays(block_map, rays[s:s + chunk], render_cfg, ids, stratified=False)
        depth.append(torch.where(out.ray_valid, out.depth_m, torch.zeros_like(out.depth_m)))
        rgb.append(out.rgb)
    h, w = frame.depth_m.shape
    return torch.cat(depth).reshape(h, w).cpu().numpy(), torch.cat(rgb).reshape(h, w, 3).cpu().numpy()
