"""Volume rendering of SDF samples (paper, "Rendering for Neural Blocks")."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class RenderOutput:
    """What rendering ``R`` rays with ``S`` samples each produced.

    Attributes:
        depth_m: ``(R,)`` rendered depth.
        rgb: ``(R, 3)`` rendered colour.
        z: ``(R, S)`` sample depths along each ray.
        sdf: ``(R, S)`` predicted SDF in truncation units (0 at invalid samples).
        sample_valid: ``(R, S)`` bool, the sample lies in a block.
        ray_valid: ``(R,)`` bool, the ray has at least one valid sample.
        observed: ``(R,)`` bool, the ray counts for the colour and depth losses (see :func:`observed_rays`).
    """

    depth_m: torch.Tensor
    rgb: torch.Tensor
    z: torch.Tensor
    sdf: torch.Tensor
    sample_valid: torch.Tensor
    ray_valid: torch.Tensor
    observed: torch.Tensor


def sdf_weights(sdf: torch.Tensor, z: torch.Tensor, sample_valid: torch.Tensor, truncation_m: float,
                eps: float = 1e-8) -> torch.Tensor:
    """Normalised weights ``w_i = sigmoid(s_i/tr) sigmoid(-s_i/tr) / sum_j w_j`` (paper, after Azinovic et al.).

    The decoder predicts the SDF in truncation units (``sdf`` = s / tr, 1 in free space at the band's
    edge); as in Co-SLAM's implementation, whose loss weights the paper adopts, that normalised value is
    divided by ``tr`` once more in the sigmoids. The bell is then about ``tr^2`` wide in metres (1 cm at
    tr = 10 cm), so free-space samples (``sdf`` = 1) get a negligible weight instead of 0.197 / 0.25 of
    a surface sample's. Samples more than ``tr`` behind the first zero crossing are dropped, so a
    second surface further along the ray cannot pull the rendered depth.

    Args:
        sdf: ``(R, S)`` normalised SDF.
        z: ``(R, S)`` increasing sample depths.
        sample_valid: ``(R, S)`` bool; invalid samples get weight 0.
    Returns:
        ``(R, S)`` weights summing to 1 on rays with a valid sample (0 elsewhere).
    """
    x = sdf / truncation_m
    w = torch.sigmoid(x) * torch.sigmoid(-x) * sample_valid.to(sdf.dtype)
    with torch.no_grad():
        s = torch.where(sample_valid, sdf, torch.ones_like(sdf))
        crossing = (s[:, :-1] > 0) & (s[:, 1:] <= 0)
        has = crossing.any(dim=1)
        first = torch.argmax(crossing.to(torch.int8), dim=1) + 1  # first sample at or behind the surface
        z_surface = torch.gather(z, 1, first[:, None])[:, 0]
        keep = ~has[:, None] | (z <= (z_surface + truncation_m)[:, None])
    w = w * keep.to(w.dtype)
    return w / (w.sum(dim=-1, keepdim=True) + eps)


def observed_rays(sample_valid: torch.Tensor, z: torch.Tensor, depth_obs: torch.Tensor,
                  truncation_m: float) -> torch.Tensor:
    """Rays whose rendered colour and depth can be compared with the observation: ``(R,)`` bool.

    A ray with measured depth counts only when a consulted block holds a sample within ``tr`` of that
    depth, i.e. the observed surface lies in the map. Otherwise its samples inside blocks are free space
    only, its normalised weights spread over them, and the rendered depth and colour are meaningless
    (they would pull a pose or train colours onto empty space). A ray without depth counts when it has
    any valid sample.
    """
    near_surface = (z - depth_obs[:, None]).abs() <= truncation_m
    has_depth = depth_obs > 0
    return sample_valid.any(dim=-1) & (~has_depth | (sample_valid & near_surface).any(dim=-1))


def composite(weights: torch.Tensor, z: torch.Tensor, rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted means: ``(R, S)`` weights, ``(R, S)`` depths, ``(R, S, 3)`` colours -> depth (R,), rgb (R, 3)."""
    return (weights * z).sum(dim=-1), (weights[..., None] * rgb).sum(dim=-2)
