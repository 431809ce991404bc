"""Mesh extraction from the block map: marching cubes per block on one world-aligned lattice.

Every block runs marching cubes (scikit-image) over its own part of a lattice shared by all blocks
(lattice points ``i * voxel_size_m`` in world coordinates), on the map's global SDF (mean features where
blocks overlap). A cell produces the same triangles whichever block computes it, so keeping in each
block only the triangles whose centroid it *owns* (the containing block with the nearest centre)
gives seams with neither cracks nor doubled walls. Only lattice points within ``cull_distance_m`` of an
observed point are evaluated, which both saves the work and culls surfaces far from any observation.

:func:`extract_block_meshes` gives the blocks' parts one by one, for a caller that re-extracts only the
blocks whose surface may have changed (:func:`affected_blocks`) and keeps the others' parts.
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
    lattice = _Lattice(block_map, cfg, observed_points)
    blocks = range(len(block_map))
    if progress:
        from tqdm import tqdm

        blocks = tqdm(blocks, desc="mesh", unit="block")
    parts = [trimesh.Trimesh(*tri, process=False) for b in blocks if (tri := lattice.owned_triangles(b)) is not None]
    if not parts:
        return trimesh.Trimesh()
    mesh = trimesh.util.concatenate(parts)
    mesh.merge_vertices(digits_vertex=6)
    mesh.remove_unreferenced_vertices()
    mesh.visual.vertex_colors = _query_colours(block_map, mesh.vertices, cfg.batch_points)
    return mesh


@torch.no_grad()
def extract_block_meshes(
    block_map: BlockMap, cfg: MeshConfig, observed_points: np.ndarray | None, block_ids
) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The parts of :func:`extract_mesh` that blocks ``block_ids`` own, each extracted on its own: block id
    -> (vertices ``(V, 3)`` float64 m, faces ``(F, 3)``, vertex colours ``(V, 3)`` uint8); a block without
    a triangle maps to empty arrays. Together over every block they are the triangles of
    :func:`extract_mesh`, which also merges vertices that coincide to 1e-6 m (the blocks' seams), so a
    caller that keeps the parts can re-extract only the blocks whose surface changed."""
    lattice = _Lattice(block_map, cfg, observed_points)
    out = {}
    for b in sorted(int(i) for i in block_ids):
        tri = lattice.owned_triangles(b)
        if tri is None:
            out[b] = (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3), dtype=np.uint8))
            continue
        verts, faces = tri
        used, faces = np.unique(faces, return_inverse=True)  # only the vertices its triangles use
        verts = verts[used]
        out[b] = (verts, faces.reshape(-1, 3), _query_colours(block_map, verts, cfg.batch_points)[:, :3])
    return out


def split_by_block(mesh: trimesh.Trimesh, block_map: BlockMap) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The triangles of ``mesh`` (of :func:`extract_mesh`) grouped by the block that owns their centroid,
    the rule the extraction keeps them by: block id -> (vertices, faces, vertex colours ``(V, 3)`` uint8),
    the vertex arrays shared by all parts. Each part is what :func:`extract_block_meshes` gives that block,
    up to the vertices merged on the seams."""
    verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(faces) == 0:
        return {}
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
    centres = block_map.centres().cpu().double().numpy()
    owner = _owner(verts[faces].mean(axis=1), centres, 0.5 * block_map.block_cfg.edge_m)
    return {int(b): (verts, faces[owner == b], colours) for b in np.unique(owner) if b >= 0}


def affected_blocks(block_map: BlockMap, cfg: MeshConfig, changed_ids) -> set[int]:
    """The blocks whose part (:func:`extract_block_meshes`) may differ after the tables of blocks
    ``changed_ids`` changed: those blocks and every block within reach of one of them. The SDF where blocks
    overlap blends their features, and a block's lattice reaches a voxel beyond its faces, so a neighbour
    that overlaps, touches or lies within two voxels has triangles that move too. The decoders, which
    every block shares, are not counted."""
    changed = sorted(int(b) for b in changed_ids)
    if not changed:
        return set()
    centres = block_map.centres().cpu().double().numpy()
    gap = np.abs(centres[:, None, :] - centres[None, changed, :]).max(axis=-1)
    near = (gap <= block_map.block_cfg.edge_m + 2 * cfg.voxel_size_m).any(axis=1)
    return {int(b) for b in np.flatnonzero(near)} | set(changed)


class _Lattice:
    """The world lattice of ``cfg.voxel_size_m`` over ``block_map`` and the observed voxels that limit where
    it is evaluated: what every block's marching cubes share."""

    def __init__(self, block_map: BlockMap, cfg: MeshConfig, observed_points: np.ndarray | None):
        self.block_map = block_map
        self.cfg = cfg
        self.centres = block_map.centres().cpu().double().numpy()
        self.half = 0.5 * block_map.block_cfg.edge_m
        self.observed_keys = None
        if observed_points is not None and len(observed_points):
            self.observed_keys = _voxels(np.asarray(observed_points), cfg.voxel_size_m)

    def owned_triangles(self, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Marching cubes over block ``b``'s part of the lattice: the vertices (world, metres) and the faces
        of the triangles whose centroid block ``b`` owns (:func:`_owner`), or None when it owns none."""
        block_map, cfg, v = self.block_map, self.cfg, self.cfg.voxel_size_m
        lo = np.floor((self.centres[b] - self.half) / v).astype(np.int64)
        hi = np.ceil((self.centres[b] + self.half) / v).astype(np.int64)
        shape = tuple(int(x) for x in hi - lo + 1)
        evaluate = _near_observations(self.observed_keys, lo, shape, math.ceil(cfg.cull_distance_m / v))
        if not evaluate.any():
            return None
        idx = np.argwhere(evaluate)
        pts = (idx + lo) * v
        sdf = np.full(shape, np.nan, dtype=np.float32)
        sdf_vals, valid = query_sdf(block_map, pts, cfg.batch_points)
        sdf[tuple(idx.T)] = np.where(valid, sdf_vals, np.nan)
        known = np.isfinite(sdf)
        # a cell is meshed only when all 8 of its corners carry a value
        cell_ok = np.zeros(shape, dtype=bool)
        c = known[:-1, :-1, :-1] & known[1:, :-1, :-1] & known[:-1, 1:, :-1] & known[:-1, :-1, 1:]
        c &= known[1:, 1:, :-1] & known[1:, :-1, 1:] & known[:-1, 1:, 1:] & known[1:, 1:, 1:]
        cell_ok[:-1, :-1, :-1] = c
        if not cell_ok.any():
            return None
        vol = np.where(known, sdf, 1.0).astype(np.float32)
        if vol[cell_ok].min() > 0 or vol[cell_ok].max() < 0:
            return None
        try:
            verts, faces, _, _ = marching_cubes(
                vol, level=0.0, spacing=(v, v, v), gradient_direction="ascent", allow_degenerate=False
            )
        except (ValueError, RuntimeError):  # no crossing at all
            return None
        # keep triangles of cells whose 8 corners all carry a value (a triangle lies inside its cell)
        centroid_idx = verts[faces].mean(axis=1) / v
        cell = np.clip(np.floor(centroid_idx).astype(np.int64), 0, np.array(shape) - 1)
        keep = cell_ok[tuple(cell.T)]
        verts = verts + lo * v
        centroid = verts[faces].mean(axis=1)
        keep &= _owner(centroid, self.centres, self.half) == b
        if not keep.any():
            return None
        return verts, faces[keep]


def _voxels(points: np.ndarray, v: float) -> np.ndarray:
    """``(K, 3)`` int64: the distinct lattice voxels (``floor(p / v)``) that ``points`` fall in, found as
    one packed integer per voxel (far faster than unique rows)."""
    keys = np.floor(points / v).astype(np.int64)
    if len(keys) == 0:
        return keys.reshape(0, 3)
    lo = keys.min(axis=0)
    rel = keys - lo
    if rel.max() >= 1 << 21:  # a span of more than 2^21 voxels per axis does not pack into 63 bits
        return np.unique(keys, axis=0)
    packed = np.unique((rel[:, 0] << 42) | (rel[:, 1] << 21) | rel[:, 2])
    mask = (1 << 21) - 1
    return np.stack([packed >> 42, (packed >> 21) & mask, packed & mask], axis=1) + lo


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


def query_sdf(block_map: BlockMap, points: np.ndarray, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """The map's SDF (truncation units) and validity at ``(N, 3)`` world points, in batches of ``batch``."""
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
