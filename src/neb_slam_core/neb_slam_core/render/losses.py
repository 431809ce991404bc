"""The five losses of the paper, as pure functions of rendered and observed quantities.

Units follow Co-SLAM, whose weights the paper adopts: the SDF loss compares metric signed distances
(``tr * sdf`` against ``d_obs - z``), the free-space loss compares the normalised prediction with 1
(the truncation distance). Per the paper, the SDF and free-space losses average over each ray's samples
first and then over the rays with valid depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import LossWeights


@dataclass
class LossTerms:
    """The five losses (scalars) and their weighted sum."""

    colour: torch.Tensor
    depth: torch.Tensor
    sdf: torch.Tensor
    free_space: torch.Tensor
    smoothness: torch.Tensor
    total: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k).detach()) for k in ("colour", "depth", "sdf", "free_space", "smoothness", "total")}


def colour_loss(rgb_pred: torch.Tensor, rgb_obs: torch.Tensor, ray_mask: torch.Tensor) -> torch.Tensor:
    """Mean squared colour error over the rays in ``ray_mask``: ``(R, 3)``, ``(R, 3)``, ``(R,)`` -> scalar."""
    m = ray_mask.to(rgb_pred.dtype)
    return (((rgb_pred - rgb_obs) ** 2).mean(dim=-1) * m).sum() / m.sum().clamp(min=1)


def depth_loss(depth_pred: torch.Tensor, depth_obs: torch.Tensor, ray_mask: torch.Tensor) -> torch.Tensor:
    """Mean squared depth error over rays with valid depth in ``ray_mask``: ``(R,)`` x3 -> scalar (m^2)."""
    m = (ray_mask & (depth_obs > 0)).to(depth_pred.dtype)
    return (((depth_pred - depth_obs) ** 2) * m).sum() / m.sum().clamp(min=1)


def sdf_losses(sdf: torch.Tensor, z: torch.Tensor, depth_obs: torch.Tensor, sample_valid: torch.Tensor,
               truncation_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """SDF loss in the truncation band and free-space loss in front of it.

    Args:
        sdf: ``(R, S)`` predicted SDF in truncation units.
        z: ``(R, S)`` sample depths.
        depth_obs: ``(R,)`` observed depth (0 invalid; such rays are ignored).
        sample_valid: ``(R, S)`` bool.
    Returns:
        (L_sdf in m^2, L_fs in truncation units^2). Samples behind the band are unconstrained (the
        surface may hide anything there), as in Co-SLAM.
    """
    has_depth = (depth_obs > 0)[:, None]
    obs_sdf = depth_obs[:, None] - z  # metres, positive in front of the surface
    band = sample_valid & has_depth & (obs_sdf.abs() <= truncation_m)
    front = sample_valid & has_depth & (obs_sdf > truncation_m)
    l_sdf = _per_ray_mean((sdf * truncation_m - obs_sdf) ** 2, band)
    l_fs = _per_ray_mean((sdf - 1.0) ** 2, front)
    return l_sdf, l_fs


def _per_ray_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over each ray's masked samples, then over rays with at least one: ``(R, S)`` -> scalar."""
    m = mask.to(values.dtype)
    n = m.sum(dim=-1)
    per_ray = (values * m).sum(dim=-1) / n.clamp(min=1)
    rays = (n > 0).to(values.dtype)
    return (per_ray * rays).sum() / rays.sum().clamp(min=1)


def smoothness_loss(features: torch.Tensor, neighbours: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Feature smoothness: ``(G, D)`` features at random points, ``(G, 3, D)`` at the points shifted by one
    step along x, y, z; mean over valid points of the summed squared differences."""
    diff = ((neighbours - features[:, None, :]) ** 2).sum(dim=(-1, -2))
    m = valid.to(diff.dtype)
    return (diff * m).sum() / m.sum().clamp(min=1)


def combine(weights: LossWeights, colour: torch.Tensor, depth: torch.Tensor, sdf: torch.Tensor,
            free_space: torch.Tensor, smoothness: torch.Tensor) -> LossTerms:
    total = (weights.colour * colour + weights.depth * depth + weights.sdf * sdf
             + weights.free_space * free_space + weights.smoothness * smoothness)
    return LossTerms(colour, depth, sdf, free_space, smoothness, total)
