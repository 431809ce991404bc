"""Frame-to-map tracking: optimise one camera pose by rendering the blocks in its frustum.

Follows the paper: N_t random pixels with valid depth, the full objective (without the smoothness
term, which does not depend on the pose), a fixed number of iterations; the pose with the lowest loss
seen is kept. Only rays with samples inside blocks contribute, so unmapped space never pulls the pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..config import RenderConfig, TrackingConfig
from ..geometry.lie import PoseSet
from ..render.rays import sample_pixels
from ..render.renderer import objective
from ..scene.block_map import BlockMap
from ..scene.freeze import frozen
from ..types import RgbdFrame


@dataclass
class TrackingResult:
    """Outcome of tracking one frame.

    Attributes:
        T_world_cam: the optimised pose (float64 4x4).
        loss: objective at that pose.
        depth_residual_m: mean |rendered - measured| depth over the valid rays at that pose.
        n_valid_rays: rays with at least one sample inside a block.
        iterations: optimisation steps taken.
    """

    T_world_cam: np.ndarray
    loss: float
    depth_residual_m: float
    n_valid_rays: int
    iterations: int


class Tracker:
    """Pose optimisation against a fixed map."""

    def __init__(self, cfg: TrackingConfig, render_cfg: RenderConfig, seed: int = 0):
        self.cfg = cfg
        self.render_cfg = render_cfg
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)

    def track(self, block_map: BlockMap, frame: RgbdFrame, T_init: np.ndarray) -> TrackingResult:
        dev = block_map.device
        px = sample_pixels(frame, self.cfg.n_rays, self.rng, valid_depth_only=True, border=self.cfg.border_px,
                           device=dev)
        if len(px) == 0:
            return TrackingResult(np.array(T_init, dtype=np.float64), float("inf"), float("inf"), 0, 0)
        s = self.render_cfg.sampling
        ids = block_map.blocks_in_frustum(T_init, frame.intrinsics, s.near_m, s.far_m)
        pose = PoseSet(T_init).to(dev)
        opt = torch.optim.Adam([pose.delta], lr=self.cfg.lr)
        best = (float("inf"), np.array(T_init, dtype=np.float64), float("inf"), 0)
        with frozen(block_map):
            for _ in range(self.cfg.iterations):
                rays = px.to_world(pose.matrices()[0])
                loss, out = objective(block_map, rays, self.render_cfg, ids, generator=self.generator,
                                      with_smoothness=False)
                n_valid = int(out.ray_valid.sum())
                value = float(loss.total.detach())
                if n_valid >= self.cfg.min_valid_rays and value < best[0]:
                    ok = out.ray_valid & (rays.depth_m > 0)
                    resid = float((out.depth_m - rays.depth_m)[ok].abs().mean().detach()) if ok.any() else float("inf")
                    best = (value, pose.numpy()[0], resid, n_valid)
                opt.zero_grad(set_to_none=True)
                loss.total.backward()
                opt.step()
        value, T, resid, n_valid = best
        if not np.isfinite(value):  # never enough valid rays
            n_valid = int(out.ray_valid.sum())
        return TrackingResult(T, value, resid, n_valid, self.cfg.iterations)
