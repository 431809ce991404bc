"""A neural block (NeB): an axis-aligned cube with its own hash grid, anchored in the world frame."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..config import HashGridConfig
from .hash_grid import HashGrid


class NeuralBlock(nn.Module):
    """Block ``block_id`` of edge ``edge_m`` centred at ``centre_world`` (metres, world frame).

    Its local coordinate maps the cube onto [0, 1]^3: ``(x - C) / edge + 1/2``. Which keyframes belong to
    it is mapping state, kept by :class:`~neb_slam_core.mapping.keyframes.KeyframeStore`.

    ``observed`` (a buffer, ``(V, V, V)`` bool with ``V = ceil(edge / observed_voxel_m)``; ``(0, 0, 0)`` when
    ``observed_voxel_m`` is 0) records the voxels of the cube that some keyframe has seen, up to its
    measured surface (:meth:`~neb_slam_core.scene.block_map.BlockMap.mark_observed`).
    """

    def __init__(
        self,
        block_id: int,
        centre_world,
        edge_m: float,
        grid_cfg: HashGridConfig,
        backend: str = "auto",
        seed: int | None = None,
        observed_voxel_m: float = 0.0,
    ):
        super().__init__()
        self.block_id = int(block_id)
        self.edge_m = float(edge_m)
        self.register_buffer("centre", torch.as_tensor(centre_world, dtype=torch.float32).reshape(3).clone())
        self.grid = HashGrid(grid_cfg, backend=backend, seed=seed)
        n = int(np.ceil(self.edge_m / observed_voxel_m - 1e-9)) if observed_voxel_m > 0 else 0
        self.register_buffer("observed", torch.zeros((n, n, n), dtype=torch.bool))

    @property
    def voxel_m(self) -> float:
        """Edge of a voxel of :attr:`observed` (0 without a record)."""
        n = self.observed.shape[0]
        return self.edge_m / n if n else 0.0

    @property
    def min_corner(self) -> torch.Tensor:
        return self.centre - 0.5 * self.edge_m

    @property
    def max_corner(self) -> torch.Tensor:
        return self.centre + 0.5 * self.edge_m

    def to_local(self, points_world: torch.Tensor) -> torch.Tensor:
        """``(N, 3)`` world points -> ``(N, 3)`` local coordinates, inside the block when in [0, 1]^3."""
        return (points_world - self.centre.to(points_world.dtype)) / self.edge_m + 0.5

    def contains(self, points_world: torch.Tensor) -> torch.Tensor:
        """``(N,)`` bool: the point lies in the closed cube."""
        half = 0.5 * self.edge_m
        return ((points_world - self.centre.to(points_world.dtype)).abs() <= half).all(dim=-1)

    def extra_repr(self) -> str:
        c = ", ".join(f"{v:.2f}" for v in self.centre.tolist())
        return f"id={self.block_id}, centre=({c}), edge={self.edge_m} m"
