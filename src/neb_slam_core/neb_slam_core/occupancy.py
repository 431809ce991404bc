"""A 2-D occupancy grid from the block map: a horizontal slice of its SDF, what a planner reads.

The slice lies at ``height_m`` in a level frame (z up; the ROS ``map`` frame, which
``T_world_level`` places in the engine's world). Each cell is evaluated at its centre:

- unknown (-1): outside every block, or in a voxel no keyframe has seen (the blocks' observed-space
  record, :meth:`~neb_slam_core.scene.block_map.BlockMap.observed`);
- occupied (100): the signed distance is at most ``occupied_m`` (default half a cell: the surface passes
  through the cell, or the cell is inside an object);
- free (0): otherwise.

The values and the row-major layout (row = y index from the origin, column = x index) are those of
nav_msgs/OccupancyGrid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .geometry.se3 import invert
from .mesh import query_sdf
from .scene.block_map import BlockMap

UNKNOWN, FREE, OCCUPIED = -1, 0, 100


@dataclass
class OccupancySlice:
    """``cells`` ``(H, W)`` int8 (row = y, column = x); cell (0, 0) has its corner at ``origin_xy`` of the
    level frame, at height ``height_m``; square cells of ``resolution_m``."""

    cells: np.ndarray
    origin_xy: tuple[float, float]
    resolution_m: float
    height_m: float


@torch.no_grad()
def occupancy_slice(
    block_map: BlockMap,
    truncation_m: float,
    T_world_level: np.ndarray,
    height_m: float,
    resolution_m: float,
    occupied_m: float | None = None,
    batch_points: int = 65536,
) -> OccupancySlice:
    """The slice of the module docstring over the blocks' extent in the level frame (a cell grid aligned
    with its x and y axes, snapped to multiples of ``resolution_m``). ``truncation_m``: the SDF's unit
    (the map stores distances in truncation units)."""
    occupied_m = 0.5 * resolution_m if occupied_m is None else occupied_m
    T = np.asarray(T_world_level, dtype=np.float64)
    if len(block_map) == 0:
        return OccupancySlice(np.zeros((0, 0), np.int8), (0.0, 0.0), resolution_m, height_m)
    half = 0.5 * block_map.block_cfg.edge_m
    centres = block_map.centres().detach().cpu().double().numpy().reshape(-1, 3)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners_world = (centres[:, None, :] + half * signs[None]).reshape(-1, 3)
    T_level_world = invert(T)
    corners = corners_world @ T_level_world[:3, :3].T + T_level_world[:3, 3]
    lo = np.floor(corners[:, :2].min(axis=0) / resolution_m) * resolution_m
    hi = np.ceil(corners[:, :2].max(axis=0) / resolution_m) * resolution_m
    w, h = (np.round((hi - lo) / resolution_m).astype(int)).tolist()
    xs = lo[0] + (np.arange(w) + 0.5) * resolution_m
    ys = lo[1] + (np.arange(h) + 0.5) * resolution_m
    gx, gy = np.meshgrid(xs, ys)  # (h, w): row = y
    level = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, height_m)], axis=1)
    world = level @ T[:3, :3].T + T[:3, 3]
    sdf, valid = query_sdf(block_map, world, batch_points)
    seen = block_map.observed(torch.as_tensor(world, dtype=torch.float32, device=block_map.device)).cpu().numpy()
    known = valid & seen
    cells = np.full(len(world), UNKNOWN, dtype=np.int8)
    cells[known] = np.where(sdf[known] * truncation_m <= occupied_m, OCCUPIED, FREE)
    return OccupancySlice(cells.reshape(h, w), (float(lo[0]), float(lo[1])), resolution_m, height_m)
