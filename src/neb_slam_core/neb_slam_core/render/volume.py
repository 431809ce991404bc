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


def sdf_weights(
    sdf: torch.Tensor, z: torch.Tensor, sample_valid: torch.Tensor, truncation_m: float, eps: float = 1e-8
) -> torch.Tensor:
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
    u, _ = _bells(sdf, z, sample_valid, truncation_m)
    return u / (u.sum(dim=-1, keepdim=True) + eps)


def _bells(
    sdf: torch.Tensor, z: torch.Tensor, sample_valid: torch.Tensor, truncation_m: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The unnormalised weights ``u`` of :func:`sdf_weights` (the bell times the valid and kept masks) and
    ``sigmoid(sdf / tr)``, which their slope needs."""
    x = sdf / truncation_m
    sig = torch.sigmoid(x)
    u = sig * torch.sigmoid(-x) * sample_valid.to(sdf.dtype)
    with torch.no_grad():
        s = torch.where(sample_valid, sdf, torch.ones_like(sdf))
        crossing = (s[:, :-1] > 0) & (s[:, 1:] <= 0)
        has = crossing.any(dim=1)
        first = torch.argmax(crossing.to(torch.int8), dim=1) + 1  # first sample at or behind the surface
        z_surface = torch.gather(z, 1, first[:, None])[:, 0]
        keep = ~has[:, None] | (z <= (z_surface + truncation_m)[:, None])
    return u * keep.to(u.dtype), sig


@torch.no_grad()
def sdf_weight_slopes(
    sdf: torch.Tensor, z: torch.Tensor, sample_valid: torch.Tensor, truncation_m: float, eps: float = 1e-8
) -> tuple[torch.Tensor, torch.Tensor]:
    """The weights of :func:`sdf_weights` and how any composite of them moves with the SDF, in closed form.

    For a per-sample quantity ``v`` that does not depend on the SDF (depth, colour), the composite
    ``V_i = sum_l w_il v_il`` has ``dV_i / d sdf_ij = a_ij (v_ij - V_i)``: with ``u`` the unnormalised
    weights and ``U_i = sum_l u_il + eps``, ``w = u / U`` gives ``dV_i / d u_ij = (v_ij - V_i) / U_i``, and the
    bell ``sigmoid(x) sigmoid(-x)`` (``x = sdf / tr``) has slope ``u (1 - 2 sigmoid(x)) / tr`` in ``sdf``. The
    kept mask is held fixed, as autograd holds it. One pass instead of a backward pass per composite.

    Returns:
        ``(R, S)`` weights ``w`` and slopes ``a``.
    """
    u, sig = _bells(sdf, z, sample_valid, truncation_m)
    norm = u.sum(dim=-1, keepdim=True) + eps
    return u / norm, u * (1.0 - 2.0 * sig) / (truncation_m * norm)


def observed_rays(
    sample_valid: torch.Tensor, z: torch.Tensor, depth_obs: torch.Tensor, truncation_m: float
) -> torch.Tensor:
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
