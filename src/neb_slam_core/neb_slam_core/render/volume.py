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
    """

    depth_m: torch.Tensor
    rgb: torch.Tensor
    z: torch.Tensor
    sdf: torch.Tensor
    sample_valid: torch.Tensor
    ray_valid: torch.Tensor


def sdf_weights(sdf: torch.Tensor, sample_valid: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Normalised weights ``w_i = sigmoid(s_i/tr) sigmoid(-s_i/tr) / sum_j w_j`` over the valid samples.

    Args:
        sdf: ``(R, S)`` SDF already divided by the truncation (s / tr).
        sample_valid: ``(R, S)`` bool; invalid samples get weight 0.
    Returns:
        ``(R, S)`` weights summing to 1 on rays with a valid sample (0 elsewhere).
    """
    w = torch.sigmoid(sdf) * torch.sigmoid(-sdf) * sample_valid.to(sdf.dtype)
    return w / (w.sum(dim=-1, keepdim=True) + eps)


def composite(weights: torch.Tensor, z: torch.Tensor, rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted means: ``(R, S)`` weights, ``(R, S)`` depths, ``(R, S, 3)`` colours -> depth (R,), rgb (R, 3)."""
    return (weights * z).sum(dim=-1), (weights[..., None] * rgb).sum(dim=-2)
