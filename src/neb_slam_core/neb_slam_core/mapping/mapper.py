"""Joint optimisation of blocks, decoders and keyframe poses over the keyframe store (the paper's
mapping / bundle adjustment)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..config import MappingConfig, RenderConfig
from ..geometry.lie import PoseSet
from ..geometry.rays import rays_world
from ..render.rays import RayBatch
from ..render.renderer import objective
from ..scene.block_map import BlockMap
from .keyframes import KeyframeStore
from .optimizer import MapOptimizer


@dataclass
class MappingResult:
    """One mapping call: steps taken, the last total loss, and the blocks whose tables it changed (a
    block no ray reached has no gradient, and Adam leaves parameters without gradient untouched)."""

    iterations: int
    loss: float
    changed_block_ids: set[int] = field(default_factory=set)


class Mapper:
    """Optimises the map (and, optionally, keyframe poses) on rays drawn from the keyframe store.

    The map optimiser lives as long as the mapper, so Adam's state carries over between calls and
    survives block allocation; keyframe poses get a fresh optimiser per call (the set of keyframes
    changes between calls), and the first keyframe is held fixed to anchor the world frame.

    :attr:`revisions` counts, per block id, the calls that changed the block's table (a block never
    changed is absent): a reader that keeps the counts it last saw knows which blocks changed since,
    whichever thread or caller ran the steps (the ROS ``mesh`` topic re-extracts only those).
    """

    def __init__(
        self, block_map: BlockMap, keyframes: KeyframeStore, cfg: MappingConfig, render_cfg: RenderConfig, seed: int = 0
    ):
        self.block_map = block_map
        self.keyframes = keyframes
        self.cfg = cfg
        self.render_cfg = render_cfg
        self.map_opt = MapOptimizer(block_map, cfg.grid_lr, cfg.decoder_lr)
        self.generator = torch.Generator().manual_seed(seed)
        self.revisions: dict[int, int] = {}

    def optimise_on_rays(self, rays: RayBatch, iterations: int) -> MappingResult:
        """Map-only optimisation on a fixed pool of world rays (the first frame's initialisation)."""
        loss_value = float("nan")
        changed: set[int] = set()
        for _ in range(iterations):
            batch = rays[torch.randint(len(rays), (self.cfg.n_rays,), generator=self.generator)]
            self.map_opt.zero_grad()
            loss, _ = objective(self.block_map, batch, self.render_cfg, None, generator=self.generator)
            loss.total.backward()
            changed |= self._blocks_with_gradient()
            self.map_opt.step()
            loss_value = float(loss.total.detach())
        self._count_revisions(changed)
        return MappingResult(iterations, loss_value, changed)

    def _blocks_with_gradient(self) -> set[int]:
        return {b.block_id for b in self.block_map.blocks if b.grid.table.grad is not None}

    def _count_revisions(self, changed: set[int]) -> None:
        for b in changed:
            self.revisions[b] = self.revisions.get(b, 0) + 1

    def optimise(
        self, iterations: int | None = None, optimise_poses: bool | None = None, fixed_until: int = 0
    ) -> MappingResult:
        """``iterations`` joint steps over all keyframes plus the newest block's keyframes; keyframes
        ``0..fixed_until`` keep their poses (keyframe 0 anchors the world frame; a loop correction also
        holds the keyframes up to the loop's older end)."""
        iterations = self.cfg.iterations if iterations is None else iterations
        optimise_poses = self.cfg.optimise_poses if optimise_poses is None else optimise_poses
        kfs = self.keyframes
        if len(kfs) == 0 or iterations == 0:
            return MappingResult(0, float("nan"))
        poses = PoseSet(kfs.poses()).to(kfs.device)
        pose_opt = None
        if optimise_poses and len(kfs) > fixed_until + 1:
            pose_opt = torch.optim.Adam([poses.delta], lr=self.cfg.pose_lr)
        newest = self.block_map.blocks[-1].block_id if len(self.block_map) > 1 else None
        newest_kfs = [] if newest is None else self.keyframes.keyframes_of_block(newest)
        loss_value = float("nan")
        changed: set[int] = set()
        for _ in range(iterations):
            idx = kfs.draw(self.cfg.n_rays, self.generator)
            if newest_kfs and self.cfg.n_rays_newest_block:
                idx = torch.cat([idx, kfs.draw(self.cfg.n_rays_newest_block, self.generator, newest_kfs)])
            dirs, rgb, depth, owner = kfs.gather(idx)
            T = poses.matrices(owner) if pose_opt is not None else poses.matrices(owner).detach()
            origins, d = rays_world(T, dirs)
            batch = RayBatch(origins, d, rgb, depth)
            self.map_opt.zero_grad()
            if pose_opt is not None:
                pose_opt.zero_grad(set_to_none=True)
            loss, _ = objective(self.block_map, batch, self.render_cfg, None, generator=self.generator)
            loss.total.backward()
            changed |= self._blocks_with_gradient()
            self.map_opt.step()
            if pose_opt is not None:
                poses.delta.grad[: fixed_until + 1] = 0.0  # a fresh Adam moves no zero-gradient pose
                pose_opt.step()
            loss_value = float(loss.total.detach())
        if pose_opt is not None:
            kfs.set_poses(poses.numpy())
        self._count_revisions(changed)
        return MappingResult(iterations, loss_value, changed)
