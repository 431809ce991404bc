"""The block map: all neural blocks, the shared decoders, and the geometry that ties them together.

Points are answered by the blocks that contain them (the mean of their hash features where several
overlap; points in none are invalid and get discarded by the caller). Work is restricted to the blocks
that intersect the current camera frustum. New blocks are allocated by the paper's tau rule and can be
added at any time without touching the others.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import nn

from ..config import BlockConfig, DecoderConfig, OneBlobConfig
from ..geometry.rays import depth_bounds
from ..types import Intrinsics
from . import _ext
from .block import NeuralBlock
from .decoders import Decoders
from .hash_grid import encode_blended
from .one_blob import OneBlob


@dataclass
class MapSample:
    """The map evaluated at ``N`` points.

    Attributes:
        sdf: ``(N,)`` signed distance in truncation units (0 where invalid).
        rgb: ``(N, 3)`` colour in [0, 1] (0 where invalid).
        valid: ``(N,)`` bool, the point lies in at least one of the queried blocks.
    """

    sdf: torch.Tensor
    rgb: torch.Tensor
    valid: torch.Tensor


@dataclass
class Allocation:
    """Outcome of the allocation test for one frame: ``tau`` and, when it allocated, the new block."""

    tau: float
    block: NeuralBlock | None


class BlockMap(nn.Module):
    """All neural blocks of a scene plus the shared one-blob encoding and decoders."""

    def __init__(
        self,
        block_cfg: BlockConfig = BlockConfig(),
        blob_cfg: OneBlobConfig = OneBlobConfig(),
        decoder_cfg: DecoderConfig = DecoderConfig(),
        grid_backend: str = "auto",
        seed: int = 0,
    ):
        super().__init__()
        self.block_cfg = block_cfg
        self.blob_cfg = blob_cfg
        self.decoder_cfg = decoder_cfg
        self.grid_backend = grid_backend
        self.seed = int(seed)
        self.blocks = nn.ModuleList()
        self.one_blob = OneBlob(blob_cfg, backend=grid_backend)
        with torch.random.fork_rng(devices=[]):  # decoder initialisation is part of the map's seed
            torch.manual_seed(self.seed)
            self.decoders = Decoders(
                self.one_blob.n_output_dims, block_cfg.grid.n_output_dims, decoder_cfg, backend=grid_backend
            )

    # ------------------------------------------------------------------ blocks

    def __len__(self) -> int:
        return len(self.blocks)

    @property
    def device(self) -> torch.device:
        return next(self.decoders.parameters()).device

    def add_block(self, centre_world) -> NeuralBlock:
        """Allocate a new block centred at ``centre_world`` (3,); existing blocks are untouched."""
        block_id = len(self.blocks)
        block = NeuralBlock(
            block_id,
            centre_world,
            self.block_cfg.edge_m,
            self.block_cfg.grid,
            backend=self.grid_backend,
            seed=self.seed * 100_003 + block_id,
            observed_voxel_m=self.block_cfg.observed_voxel_m,
        )
        self.blocks.append(block.to(self.device))
        return block

    def centres(self) -> torch.Tensor:
        """``(M, 3)`` block centres."""
        if not len(self.blocks):
            return torch.zeros(0, 3, device=self.device)
        return torch.stack([b.centre for b in self.blocks])

    def contains(self, points_world: torch.Tensor, block_ids: list[int] | None = None) -> torch.Tensor:
        """``(N, M)`` bool: point n lies in block ``block_ids[m]`` (all blocks when None)."""
        ids = list(range(len(self.blocks))) if block_ids is None else list(block_ids)
        return self._face_distance(points_world, self.centres()[ids]) >= 0

    def _face_distance(self, points_world: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """``(N, M)`` distance from each point to the nearest face of the block centred at ``centres[m]``,
        negative outside (half the edge minus the Chebyshev distance to the centre): containment and
        blend weights in one."""
        half = 0.5 * self.block_cfg.edge_m
        return half - (points_world[:, None, :] - centres.to(points_world.dtype)[None]).abs().amax(dim=-1)

    def blocks_in_frustum(
        self, T_world_cam: np.ndarray, intrinsics: Intrinsics, near_m: float, far_m: float
    ) -> list[int]:
        """Ids of the blocks that may intersect the camera frustum between ``near_m`` and ``far_m``.

        Conservative: a block is dropped only when all its corners lie outside one frustum plane, or all
        frustum corners lie outside one face of the block; it never drops a block that intersects.
        """
        if not len(self.blocks):
            return []
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
        centres = self.centres().detach().cpu().double().numpy()
        half = 0.5 * self.block_cfg.edge_m
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        corners_w = centres[:, None, :] + half * signs[None]  # (M, 8, 3)
        corners_c = corners_w @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        x, y, z = corners_c[..., 0], corners_c[..., 1], corners_c[..., 2]
        k = intrinsics
        outside = (
            (z < near_m).all(-1)
            | (z > far_m).all(-1)
            | (k.fx * x + k.cx * z < 0).all(-1)  # u < 0
            | (k.fx * x + (k.cx - k.width) * z > 0).all(-1)  # u > W
            | (k.fy * y + k.cy * z < 0).all(-1)  # v < 0
            | (k.fy * y + (k.cy - k.height) * z > 0).all(-1)  # v > H
        )
        # frustum corners (pixel-grid corners at near and far) against the block's faces
        uv = np.array([[0, 0], [k.width, 0], [0, k.height], [k.width, k.height]], dtype=np.float64)
        rays = np.stack([(uv[:, 0] - k.cx) / k.fx, (uv[:, 1] - k.cy) / k.fy, np.ones(4)], axis=1)
        fr_c = np.concatenate([rays * near_m, rays * far_m])  # (8, 3)
        fr_w = fr_c @ np.asarray(T_world_cam)[:3, :3].T + np.asarray(T_world_cam)[:3, 3]
        lo, hi = centres - half, centres + half  # (M, 3)
        outside |= ((fr_w[None] < lo[:, None]).all(1) | (fr_w[None] > hi[:, None]).all(1)).any(-1)
        return [i for i in range(len(self.blocks)) if not outside[i]]

    # ------------------------------------------------------------------ queries

    def grid_features(
        self, points_world: torch.Tensor, block_ids: list[int] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Hash features averaged over the containing blocks (weighted by the blend window, see
        :class:`~neb_slam_core.config.BlockConfig`).

        Args:
            points_world: ``(N, 3)`` world points.
            block_ids: blocks to consult (e.g. the frustum's); all when None.
        Returns:
            ``(N, L*F)`` features (0 for points in no block) and ``(N,)`` bool validity.
        """
        ids = list(range(len(self.blocks))) if block_ids is None else list(block_ids)
        n = points_world.shape[0]
        dim = self.block_cfg.grid.n_output_dims
        centres = self.centres()[ids].to(points_world.dtype)
        if len(ids) > 1:
            # without gradients, the C++ kernel does the whole blend in one pass (same sum as below)
            blended = encode_blended(
                points_world, centres, [self.blocks[i].grid for i in ids], self.block_cfg.edge_m, self.block_cfg.blend_m
            )
            if blended is not None:
                return blended
        to_face = self._face_distance(points_world, centres)  # (N, M)
        inside = to_face >= 0
        valid = inside.any(dim=1)
        if len(ids) == 1:
            # the common case (one block in view): no gather/scatter; points outside are clamped by
            # the grid and masked here
            block = self.blocks[ids[0]]
            feats = block.grid(block.to_local(points_world).clamp(0.0, 1.0))
            return feats * valid[:, None].to(feats.dtype), valid
        feats = points_world.new_zeros(n, dim)
        weight_sum = points_world.new_zeros(n)
        # All (point, block) pairs at once, grouped by block: one gather, one blend and one scatter for
        # every block in view rather than one per block (their fixed cost is what a view seeing several
        # blocks paid over a view seeing one); only the encoding itself runs per block, on its slice.
        block_of, point_of = inside.T.nonzero(as_tuple=True)
        if point_of.numel() == 0:
            return feats, valid
        counts = inside.sum(dim=0).tolist()
        local = (points_world[point_of] - centres[block_of]) / self.block_cfg.edge_m + 0.5
        encoded = torch.cat(
            [self.blocks[block_id].grid(chunk) for block_id, chunk in zip(ids, local.split(counts)) if chunk.shape[0]]
        )
        w = self._blend_weight(to_face[point_of, block_of])
        # in place: an out-of-place index_add copies the whole (N, L*F) tensor
        feats.index_add_(0, point_of, encoded.to(feats.dtype) * w[:, None])
        weight_sum.index_add_(0, point_of, w)
        feats = feats / weight_sum.clamp(min=1e-12)[:, None]
        return feats, valid

    def _blend_weight(self, to_face: torch.Tensor) -> torch.Tensor:
        """Window weight of a block at points inside it, from their distance ``to_face`` to its nearest
        face: 1 deeper than ``blend_m``, falling linearly to a tiny positive value at the faces (never
        exactly 0, so a point inside a single block keeps its features)."""
        blend = self.block_cfg.blend_m
        if blend <= 0:
            return torch.ones_like(to_face)
        return (to_face / blend).clamp(min=1e-6, max=1.0)

    def query(
        self, points_world: torch.Tensor, block_ids: list[int] | None = None, with_colour: bool = True
    ) -> MapSample:
        """Evaluate SDF and colour at ``(N, 3)`` world points (0 at invalid points).

        The decoders run on every point (dense, no scatter); invalid points are masked afterwards,
        which is cheaper on CPU than compacting when most samples lie in blocks, as they do.
        """
        feats, valid = self.grid_features(points_world, block_ids)
        blob = self.one_blob(points_world)
        mask = valid.to(feats.dtype)
        if with_colour:
            sdf, rgb = self.decoders(blob, feats)
            return MapSample(sdf * mask, rgb * mask[:, None], valid)
        sdf = self.decoders.sdf_only(blob, feats)
        return MapSample(sdf * mask, points_world.new_zeros(points_world.shape[0], 3), valid)

    def spatial_gradients(self, points_world: torch.Tensor, block_ids: list[int] | None = None) -> torch.Tensor | None:
        """``(4, N, 3)``: the derivatives of SDF, red, green and blue w.r.t. ``(N, 3)`` world points (0 at
        points in none of the blocks), in closed form: the C++ kernel's features with their derivatives
        (:func:`~.hash_grid.encode_blended`), the one-blob slopes, and the decoders' forward mode. What
        autograd gives through :meth:`query`, at one encoding pass instead of a backward pass per output.
        None when that kernel does not apply (reference backend, not on the CPU); the caller then
        differentiates otherwise (tracking: forward differences)."""
        ids = list(range(len(self.blocks))) if block_ids is None else list(block_ids)
        if not ids:
            return None
        with torch.no_grad():
            encoded = encode_blended(
                points_world,
                self.centres()[ids],
                [self.blocks[i].grid for i in ids],
                self.block_cfg.edge_m,
                self.block_cfg.blend_m,
                jacobian=True,
            )
            if encoded is None:
                return None
            feats, valid, d_feats = encoded
            blob, slopes = self.one_blob.with_slopes(points_world.to(feats.dtype))
            _, _, d_sdf, d_rgb = self.decoders.forward_with_tangents(blob, feats, slopes, d_feats)
            grads = torch.cat([d_sdf[..., None], d_rgb], dim=-1)  # (N, axis, output)
            return grads.permute(2, 0, 1) * valid[None, :, None].to(grads.dtype)

    # ------------------------------------------------------------------ observed space

    def mark_observed(
        self, depth_m: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray, truncation_m: float
    ) -> set[int]:
        """Record the space a keyframe saw: every voxel of every block whose centre projects into the depth
        image ``depth_m`` (H, W) at ``T_world_cam`` onto a pixel with depth, no deeper than that depth plus
        ``truncation_m`` (the SDF band behind the surface) plus half a voxel diagonal (a point in the
        voxel may lie that much nearer than its centre). The depth a centre is compared with is the
        deepest within the voxel's footprint (its width in pixels at the frame's median depth). Only
        voxels in the bounding box of the camera centre and the back-projected surface are tested.
        Returns the ids of the blocks with newly observed voxels; nothing without a record
        (``block.observed_voxel_m`` 0)."""
        if not len(self.blocks) or self.blocks[0].voxel_m <= 0:
            return set()
        depth = np.asarray(depth_m, dtype=np.float32)
        valid = depth > 0
        if not valid.any():
            return set()
        T = np.asarray(T_world_cam, dtype=np.float64)
        k = intrinsics
        lo, hi = depth_bounds(np.where(valid, depth + truncation_m, 0.0), k, T)  # the band's far side
        lo, hi = np.minimum(lo, T[:3, 3]), np.maximum(hi, T[:3, 3])
        dev = self.device
        R_cw = T[:3, :3].T
        t_cw = torch.as_tensor(-R_cw @ T[:3, 3], dtype=torch.float32, device=dev)
        # a voxel's footprint at the frame's median depth: a voxel counts as seen where any pixel of its
        # footprint saw through it (the deepest), so holes and depth edges of a real sensor do not
        # punch unobserved voxels into surfaces the frame saw
        half = int(0.5 * k.fx * self.blocks[0].voxel_m / float(np.median(depth[valid])))
        if half > 0:  # the maximum over the square footprint: a grey dilation (OpenCV's is separable)
            depth = cv2.dilate(depth, np.ones((2 * half + 1, 2 * half + 1), np.uint8))
        depth_t = torch.as_tensor(np.ascontiguousarray(depth), device=dev)
        # the C++ kernel where the map runs the fast path (the backend rule of every module with one)
        on_cpu = dev.type == "cpu"
        fast = _ext.use_fast_path(self.grid_backend, on_cpu, "BlockMap.mark_observed", f"a CPU map; got {dev}")
        kernels = _ext.load_map_kernels() if fast else None
        grown = set()
        for block in self.blocks:
            n, vox = block.observed.shape[0], block.voxel_m
            corner = block.min_corner.detach().cpu().double().numpy()
            i0 = np.clip(np.floor((lo - corner) / vox).astype(int), 0, n)
            i1 = np.clip(np.ceil((hi - corner) / vox).astype(int), 0, n)
            if np.any(i1 <= i0):
                continue
            # the voxel centres' camera coordinates R^T (c - t) are a sum of one term per world axis, so the
            # box's are three small tables broadcast together, not a matrix product per voxel
            terms = [
                torch.as_tensor(
                    np.outer(corner[a] + (np.arange(i0[a], i1[a]) + 0.5) * vox, R_cw[:, a]),
                    dtype=torch.float32,
                    device=dev,
                )
                for a in range(3)
            ]
            half_diagonal = 0.5 * np.sqrt(3.0) * vox
            if kernels is not None:
                box = torch.as_tensor(np.concatenate([i0, i1]), dtype=torch.int64)
                grew = kernels.mark_observed_box(
                    block.observed, box, *terms, t_cw, depth_t, k.fx, k.fy, k.cx, k.cy, truncation_m, half_diagonal
                )
            else:
                grew = _mark_box(block.observed, i0, i1, terms, t_cw, depth_t, k, truncation_m, half_diagonal)
            if grew:
                grown.add(block.block_id)
        return grown

    def observed(self, points_world: torch.Tensor, block_ids: list[int] | None = None) -> torch.Tensor:
        """``(N,)`` bool: the point lies in an observed voxel (:meth:`mark_observed`) of one of the blocks
        ``block_ids`` (all when None) that contain it. Without a record (``block.observed_voxel_m`` 0)
        every point counts as observed."""
        ids = list(range(len(self.blocks))) if block_ids is None else list(block_ids)
        if not ids or self.blocks[ids[0]].voxel_m <= 0:
            return torch.ones(points_world.shape[0], dtype=torch.bool, device=points_world.device)
        out = torch.zeros(points_world.shape[0], dtype=torch.bool, device=points_world.device)
        for i in ids:
            block = self.blocks[i]
            n = block.observed.shape[0]
            idx = torch.floor(block.to_local(points_world.detach()) * n).long()
            inside = ((idx >= 0) & (idx < n)).all(dim=-1)
            idx = idx.clamp(0, n - 1)
            out |= inside & block.observed[idx[:, 0], idx[:, 1], idx[:, 2]]
        return out

    # ------------------------------------------------------------------ allocation

    def allocation_tau(self, points_world: torch.Tensor, block_ids: list[int]) -> tuple[float, torch.Tensor]:
        """tau = fraction of ``(N, 3)`` back-projected points outside every block in ``block_ids``;
        also returns the outside points ``(K, 3)``."""
        if points_world.shape[0] == 0:
            return 0.0, points_world
        inside = self.contains(points_world, block_ids).any(dim=1)
        outside = points_world[~inside]
        return float(outside.shape[0]) / points_world.shape[0], outside

    def allocate_if_needed(self, points_world: torch.Tensor, block_ids: list[int]) -> Allocation:
        """The paper's rule: when tau > threshold, add a block centred at the mean of the outside points;
        with ``block.alloc_centre`` ``cover``, moved by :func:`covering_centre` where another cube covers
        more of them."""
        tau, outside = self.allocation_tau(points_world, block_ids)
        cfg = self.block_cfg
        if tau <= cfg.alloc_threshold or outside.shape[0] == 0:
            return Allocation(tau, None)
        centre = outside.mean(dim=0)
        if cfg.alloc_centre == "cover":
            centre = covering_centre(outside, centre, 0.5 * cfg.edge_m)
        return Allocation(tau, self.add_block(centre.detach()))

    # ------------------------------------------------------------------ sizes

    def grid_param_bytes(self) -> int:
        return sum(b.grid.param_bytes for b in self.blocks)

    def decoder_param_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.decoders.parameters())

    def param_mb(self) -> float:
        """Parameter size in MB (10^6 bytes): blocks x per-block grid + decoders."""
        return (self.grid_param_bytes() + self.decoder_param_bytes()) / 1e6


def _mark_box(
    observed: torch.Tensor,
    i0: np.ndarray,
    i1: np.ndarray,
    terms: list[torch.Tensor],
    t_cw: torch.Tensor,
    depth: torch.Tensor,
    k: Intrinsics,
    truncation_m: float,
    half_diagonal: float,
) -> bool:
    """The torch path of :meth:`BlockMap.mark_observed` for one block: mark the voxels of the box
    ``[i0, i1)`` of ``observed`` that the depth image ``depth`` (H, W) saw, from the per-axis tables
    ``terms`` of the voxel centres' camera coordinates and ``t_cw``; whether any was new. The C++ kernel
    (``csrc/observed_kernels.h``) does the same arithmetic in the same order."""
    # the box's record, a view: marking it marks the block's (a voxel once seen stays seen)
    box = observed[i0[0] : i1[0], i0[1] : i1[1], i0[2] : i1[2]]
    unseen = ~box
    if not bool(unseen.any()):
        return False
    h, w = depth.shape
    cam = terms[0][:, None, None] + terms[1][None, :, None] + terms[2][None, None, :] + t_cw
    zc = cam[..., 2]
    in_front = zc > 1e-6
    zs = torch.where(in_front, zc, torch.ones_like(zc))
    px = torch.round(k.fx * cam[..., 0] / zs + k.cx)
    py = torch.round(k.fy * cam[..., 1] / zs + k.cy)
    inside = unseen & in_front & (px >= 0) & (px < w) & (py >= 0) & (py < h)
    pixel = py.clamp(0, h - 1).long() * w + px.clamp(0, w - 1).long()
    d = depth.reshape(-1)[pixel]
    seen = inside & (d > 0) & (zc <= d + truncation_m + half_diagonal)
    if not bool(seen.any()):
        return False
    box |= seen
    return True


def covering_centre(points: torch.Tensor, start: torch.Tensor, half_edge_m: float) -> torch.Tensor:
    """The centre of a cube of half-edge ``half_edge_m`` for a new block over ``points`` ``(K, 3)`` (the
    points outside every block): of ``start`` (the paper's mean) and the steps of a mean shift from it,
    the one whose cube holds the most points; ``start`` where none holds more.

    Where the outside points lie on two sides of the mapped space (a camera in a room's corner looking
    past the blocks both ways), their mean falls between them, next to the blocks there: its block covers
    little of either side and overlaps the blocks beside it (every point in an overlap is encoded once
    per block), and the next frames allocate again between the sides. A mean shift with the block's cube
    as its window (each step: the mean of the points inside the cube) climbs to one side's densest cube;
    the next frame allocates for the other side if it still needs a block. Where the mean's cube holds
    every outside point (one region of new space) the paper's centre stays."""

    def inside(c: torch.Tensor) -> torch.Tensor:
        return (points - c).abs().amax(dim=-1) <= half_edge_m

    mask = inside(start)
    n_start = int(mask.sum())
    if n_start == points.shape[0]:
        return start
    best, best_n = start, n_start
    centre = start
    for _ in range(20):  # a flat-window mean shift converges in a few steps
        if not mask.any():  # the window holds no point: restart at the nearest one
            mask = torch.zeros_like(mask)
            mask[(points - centre).abs().amax(dim=-1).argmin()] = True
        shifted = points[mask].mean(dim=0)
        if torch.equal(shifted, centre):  # converged: its cube was counted when it was reached
            break
        mask = inside(shifted)
        n = int(mask.sum())
        if n > n_start and n >= best_n:  # on a tie between steps, the later (more central) one
            best, best_n = shifted, n
        centre = shifted
    return best
