"""Render ray batches through the block map and score them with the paper's objective."""

from __future__ import annotations

import torch

from ..config import RenderConfig, SamplingConfig
from ..scene.block_map import BlockMap, MapSample
from .losses import Objective, Residual, combine, render_residuals, smoothness_residual
from .rays import RayBatch
from .sampling import evaluated_samples, sample_depths
from .volume import RenderOutput, composite, observed_rays, sdf_weights


def query_samples(
    block_map: BlockMap,
    points: torch.Tensor,
    z: torch.Tensor,
    depth_m: torch.Tensor,
    sampling: SamplingConfig,
    block_ids: list[int] | None = None,
    with_colour: bool = True,
    observed_only: bool = False,
) -> MapSample:
    """The map at the ``(R, S, 3)`` sample points of ``R`` rays (depths ``z`` (R, S), measured depth
    ``depth_m`` (R,)), flattened to ``R * S``. Samples too far behind the measured depth
    (:func:`~neb_slam_core.render.sampling.evaluated_samples`) are not evaluated and come back invalid,
    as if outside every block; gradients reach the evaluated ones only. With ``observed_only``, so do
    samples in space no keyframe has seen (:meth:`~neb_slam_core.scene.block_map.BlockMap.observed`)."""
    flat = points.reshape(-1, 3)
    keep = evaluated_samples(z, depth_m, sampling.skip_behind_m)
    if observed_only:
        seen = block_map.observed(flat, block_ids).reshape(z.shape)
        keep = seen if keep is None else keep & seen
    if keep is None or bool(keep.all()):
        return block_map.query(flat, block_ids, with_colour=with_colour)
    idx = keep.reshape(-1).nonzero(as_tuple=True)[0]
    part = block_map.query(flat[idx], block_ids, with_colour=with_colour)
    n = flat.shape[0]
    return MapSample(
        part.sdf.new_zeros(n).index_copy(0, idx, part.sdf),
        part.rgb.new_zeros(n, 3).index_copy(0, idx, part.rgb),
        part.valid.new_zeros(n).index_copy(0, idx, part.valid),
    )


def render_rays(
    block_map: BlockMap,
    rays: RayBatch,
    cfg: RenderConfig,
    block_ids: list[int] | None = None,
    stratified: bool = True,
    generator: torch.Generator | None = None,
    with_colour: bool = True,
    z: torch.Tensor | None = None,
    observed_only: bool = False,
) -> RenderOutput:
    """Sample, query the blocks ``block_ids`` (all when None) and composite ``R`` rays.

    Samples outside every consulted block are discarded (weight 0), as the paper prescribes, and so are
    samples too far behind the measured depth and, with ``observed_only``, samples in space no keyframe
    has seen (:func:`query_samples`). ``z`` (R, S) gives the sample depths instead of drawing them.
    """
    if z is None:
        z = sample_depths(rays.depth_m, cfg.sampling, stratified=stratified, generator=generator)  # (R, S)
    r, s = z.shape
    points = rays.origins[:, None, :] + z[..., None] * rays.dirs[:, None, :]  # (R, S, 3)
    sample = query_samples(block_map, points, z, rays.depth_m, cfg.sampling, block_ids, with_colour, observed_only)
    sdf = sample.sdf.reshape(r, s)
    valid = sample.valid.reshape(r, s)
    w = sdf_weights(sdf, z, valid, cfg.truncation_m)
    depth, rgb = composite(w, z, sample.rgb.reshape(r, s, 3))
    return RenderOutput(
        depth, rgb, z, sdf, valid, valid.any(dim=-1), observed_rays(valid, z, rays.depth_m, cfg.truncation_m)
    )


def smoothness_term(
    block_map: BlockMap, cfg: RenderConfig, block_ids: list[int] | None, generator: torch.Generator | None = None
) -> Residual | None:
    """Feature smoothness on ``cfg.smoothness_points`` random points of random consulted blocks (None when
    the term is off or no block is consulted)."""
    ids = list(range(len(block_map))) if block_ids is None else list(block_ids)
    g = cfg.smoothness_points
    if not ids or g == 0 or cfg.weights.smoothness == 0:
        return None
    dev = block_map.device
    which = torch.randint(len(ids), (g,), device=dev, generator=generator)
    centres = block_map.centres()[torch.as_tensor(ids, device=dev)[which]]
    edge = block_map.block_cfg.edge_m
    step = cfg.smoothness_step_m
    offsets = torch.rand(g, 3, device=dev, generator=generator) * (edge - step) - 0.5 * edge
    p = centres + offsets
    shifted = p[:, None, :] + step * torch.eye(3, device=dev)[None]  # (G, 3, 3)
    pts = torch.cat([p, shifted.reshape(-1, 3)])
    feats, valid = block_map.grid_features(pts, ids)
    f0, f1 = feats[:g], feats[g:].reshape(g, 3, -1)
    v = valid[:g] & valid[g:].reshape(g, 3).all(dim=1)
    return smoothness_residual(cfg.weights.smoothness, f0, f1, v)


def objective(
    block_map: BlockMap,
    rays: RayBatch,
    cfg: RenderConfig,
    block_ids: list[int] | None = None,
    generator: torch.Generator | None = None,
    with_smoothness: bool = True,
    z: torch.Tensor | None = None,
    observed_only: bool = False,
) -> tuple[Objective, RenderOutput]:
    """Render ``rays`` and evaluate the paper's weighted objective on them (at sample depths ``z`` when
    given, else stratified ones; ``observed_only``: see :func:`render_rays`)."""
    out = render_rays(
        block_map, rays, cfg, block_ids, stratified=True, generator=generator, z=z, observed_only=observed_only
    )
    terms = render_residuals(
        cfg.weights,
        cfg.truncation_m,
        out.rgb,
        out.depth_m,
        out.sdf,
        out.z,
        out.sample_valid,
        out.observed,
        rays.rgb,
        rays.depth_m,
        cfg.depth_noise_weights,
    )
    smooth = smoothness_term(block_map, cfg, block_ids, generator) if with_smoothness else None
    if smooth is not None:
        terms["smoothness"] = smooth
    return combine(terms), out
