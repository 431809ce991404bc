"""Bound-free one-blob encoding of world coordinates.

One-blob (Mueller et al., "Neural Importance Sampling") turns a scalar in [0, 1) into ``K`` bins, each
the value of a Gaussian of width 1/K centred on the bin, evaluated at the scalar. Co-SLAM applies it to
coordinates normalised by the scene bounds; an unknown scene has none, so we encode each world axis by
its phase ``x / period mod 1`` and measure the distance to a bin centre on the circle. The code is
therefore smooth everywhere and needs no bounds; it repeats every ``period_m`` metres, which the
per-block hash features disambiguate.
"""

from __future__ import annotations

import torch

from ..config import OneBlobConfig


class OneBlob(torch.nn.Module):
    """``(N, 3)`` world points (metres) -> ``(N, 3 * n_bins)`` codes in [0, 1], differentiable in the points."""

    def __init__(self, cfg: OneBlobConfig = OneBlobConfig()):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("centres", (torch.arange(cfg.n_bins, dtype=torch.float32) + 0.5) / cfg.n_bins,
                             persistent=False)

    @property
    def n_output_dims(self) -> int:
        return 3 * self.cfg.n_bins

    def forward(self, points_world: torch.Tensor) -> torch.Tensor:
        k = self.cfg.n_bins
        phase = torch.remainder(points_world / self.cfg.period_m, 1.0)  # (N, 3)
        d = (phase[..., None] - self.centres.to(points_world.dtype)).abs()  # (N, 3, K)
        d = torch.minimum(d, 1.0 - d)  # distance on the circle
        code = torch.exp(-0.5 * (d * k) ** 2)  # sigma = 1 / K
        return code.flatten(-2)
