"""The two shared decoders of the paper (sizes from Co-SLAM, which NeB-SLAM follows).

geometry f_gamma: [one-blob (48) | hash features (32)] -> 32 -> [sdf (1) | feature g (15)]
colour   f_delta: [one-blob (48) | g (15)]             -> 32 -> rgb (3)

The SDF is predicted in units of the truncation distance (1 = free space at the band's edge); the
renderer multiplies by ``truncation_m`` where metres are needed.
"""

from __future__ import annotations

import torch
from torch import nn

from ..config import DecoderConfig


def _mlp(n_in: int, n_hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, n_hidden), nn.ReLU(inplace=True), nn.Linear(n_hidden, n_out))


class Decoders(nn.Module):
    """Geometry and colour MLPs shared by all blocks."""

    def __init__(self, n_blob_dims: int, n_grid_dims: int, cfg: DecoderConfig = DecoderConfig()):
        super().__init__()
        self.cfg = cfg
        self.geometry = _mlp(n_blob_dims + n_grid_dims, cfg.hidden_dim, 1 + cfg.feature_dim)
        self.colour = _mlp(n_blob_dims + cfg.feature_dim, cfg.hidden_dim, 3)

    def forward(self, blob: torch.Tensor, grid_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``blob`` (N, 48), ``grid_features`` (N, 32) -> (sdf in truncation units (N,), rgb in [0, 1] (N, 3))."""
        h = self.geometry(torch.cat([blob, grid_features], dim=-1))
        sdf, g = h[..., 0], h[..., 1:]
        rgb = torch.sigmoid(self.colour(torch.cat([blob, g], dim=-1)))
        return sdf, rgb

    def sdf_only(self, blob: torch.Tensor, grid_features: torch.Tensor) -> torch.Tensor:
        """The SDF alone (skips the colour MLP): (N,)."""
        return self.geometry(torch.cat([blob, grid_features], dim=-1))[..., 0]
