"""Mesh extraction from the block map: marching cubes per block on one world-aligned lattice.

Every block runs marching cubes (scikit-image) over its own part of a lattice shared by all blocks
(lattice points ``i * voxel_size_m`` in world coordinates), on the map's global SDF (mean features where
blocks overlap). A cell produces the same triangles whichever block computes it, so keeping in each
block only the triangles whose centroid it *owns* (the containing block with the nearest centre)
gives seams with neither cracks nor doubled walls. Only lattice points within ``cull_distance_m`` of an
observed point are evaluated, which both saves the work and culls surfaces far from any observation.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh
from scipy import ndimage
from skimage.measure import marching_cubes

from .config import MeshConfig
from .scene.block_map import BlockMap


@torch.no_grad()
def extract_mesh(
    block_map: BlockMap, cfg: MeshConfig, observed_points: np.ndarray | None = None, progress: bool = False
) -> trimesh.Trimesh:
    """The zero level set of the map's SDF as a coloured triangle mesh (world frame, metres).

    Args:
        block_map: the map.
        cfg: voxel size, culling distance, evaluation batch size.
        observed_points: ``(K, 3)`` world points the cameras observed (e.g. back-projected keyframe
            depth). Surfaces farther than ``cfg.cull_distance_m`` from all of them are not extracted.
            None evaluates every block completely (slow for large blocks; no culling).
    """
    v = cfg.voxel_size_m
    centres = block_map.centres().cpu().double().numpy()
    half = 0.5 * block_map.block_cfg.edge_m
    observed_keys = None
    if observed_points is not None and len(observed_points):
        observed_keys = np.unique(np.floor(np.asarray(observed_points) / v).astype(np.int64), axis=0)
    parts: list[trimesh.Trimesh] = []
    blocks = range(len(block_map))
    if progress:
        from tqdm import tqdm

        blocks = tqdm(blocks, desc="mesh", unit="block")
    for b in blocks:
        lo = np.floor((centres[b] - half) / v).astype(np.int64)
        hi = np.ceil((centres[b] + half) / v).astype(np.int64)
        shape = tuple(int(x) for x in hi - lo + 1)
        evaluate = _near_observations(observed_keys, lo, shape, math.ceil(cfg.cull_distance_m / v))
        if not evaluate.any():
            continue
        idx = np.argwhere(evaluate)
        pts = (idx + lo) * v
        sdf = np.full(shape, np.nan, dtype=np.float32)
        sdf_vals, valid = _query_sdf(block_map, pts, cfg.batch_points)
        sdf[tuple(idx.T)] = np.where(valid, sdf_vals, np.nan)
        known = np.isfinite(sdf)
        # a cell is meshed only when all 8 of its corners carry a value
        cell_ok = np.zeros(shape, dtype=bool)
        c = known[:-1, :-1, :-1] & known[1:, :-1, :-1] & known[:-1, 1:, :-1] & known[:-1, :-1, 1:]
        c &= known[1:, 1:, :-1] & known[1:, :-1, 1:] & known[:-1, 1:, 1:] & known[1:, 1:, 1:]
        cell_ok[:-1, :-1, :-1] = c
        if not cell_ok.any():
            continue
        vol = np.where(known, sdf, 1.0).astype(np.float32)
        if vol[cell_ok].min() > 0 or vol[cell_ok].max() < 0:
            continue
        try:
            verts, faces, _, _ = marching_cubes(
                vol, level=0.0, spacing=(v, v, v), gradient_direction="ascent", allow_degenerate=False
            )
        except (ValueError, RuntimeError):  # no crossing at all
            continue
        # keep triangles of cells whose 8 corners all carry a value (a triangle lies inside its cell)
        centroid_idx = verts[faces].mean(axis=1) / v
        cell = np.clip(np.floor(centroid_idx).astype(np.int64), 0, np.array(shape) - 1)
        keep = cell_ok[tuple(cell.T)]
        verts = verts + lo * v
        centroid = verts[faces].mean(axis=1)
        keep &= _owner(centroid, centres, half) == b
        if not keep.any():
            continue
        parts.append(trimesh.Trimesh(verts, faces[keep], process=False))
    if not parts:
        return trimesh.Trimesh()
    mesh = trimesh.util.concatenate(parts)
    mesh.merge_vertices(digits_vertex=6)
    mesh.remove_unreferenced_vertices()
    mesh.visual.vertex_colors = _query_colours(block_map, mesh.vertices, cfg.batch_points)
    return mesh


def _near_observations(
    observed_keys: np.ndarray | None, lo: np.ndarray, shape: tuple[int, int, int], radius_voxels: int
) -> np.ndarray:
    """``shape`` bool grid: lattice points within ``radius_voxels`` (Chebyshev) of an observed voxel."""
    if observed_keys is None:
        return np.ones(shape, dtype=bool)
    rel = observed_keys - lo
    inside = np.all((rel >= 0) & (rel < np.array(shape)), axis=1)
    grid = np.zeros(shape, dtype=bool)
    grid[tuple(rel[inside].T)] = True
    # the voxel of a point spans lattice points key..key+1, so dilate by one more
    size = 2 * (radius_voxels + 1) + 1
    return ndimage.maximum_filter(grid, size=size, mode="constant", cval=0).astype(bool)


def _owner(points: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """Index of the block owning each ``(N, 3)`` point: the containing block with the nearest centre (-1: none)."""
    d = np.linalg.norm(points[:, None, :] - centres[None], axis=-1)
    inside = np.all(np.abs(points[:, None, :] - centres[None]) <= half + 1e-9, axis=-1)
    d[~inside] = np.inf
    owner = np.argmin(d, axis=1)
    owner[~inside.any(axis=1)] = -1
    return owner


def _query_sdf(block_map: BlockMap, points: np.ndarray, batch: int) -> tuple[np.ndarray, np.ndarray]:
    dev = block_map.device
    sdf, valid = [], []
    for s in range(0, len(points), batch):
        p = torch.as_tensor(points[s : s + batch], dtype=torch.float32, device=dev)
        q = block_map.query(p, with_colour=False)
        sdf.append(q.sdf.cpu().numpy())
        valid.append(q.valid.cpu().numpy())
    return np.concatenate(sdf), np.concatenate(valid)


def _query_colours(block_map: BlockMap, points: np.ndarray, batch: int) -> np.ndarray:
    dev = block_map.device
    out = []
    for s in range(0, len(points), batch):
        p = torch.as_tensor(points[s : s + batch], dtype=torch.float32, device=dev)
        out.append(block_map.query(p).rgb.cpu().numpy())
    rgb = (np.clip(np.concatenate(out), 0, 1) * 255).round().astype(np.uint8)
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)


def save_mesh(mesh: trimesh.Trimesh, path) -> None:
    """Write ``mesh`` as binary PLY with vertex colours."""
    mesh.export(str(path), file_type="ply")
