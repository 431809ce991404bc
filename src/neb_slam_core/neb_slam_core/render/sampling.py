"""Samples along rays: N1 uniform between near and far plus N2 around the measured depth."""

from __future__ import annotations

import torch

from ..config import SamplingConfig


def sample_depths(
    depth_m: torch.Tensor, cfg: SamplingConfig, stratified: bool = True, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Ray parameters (z-depths) of the samples, sorted along each ray.

    Args:
        depth_m: ``(R,)`` measured depth, 0 where invalid.
        stratified: jitter each sample within its bin (training); bin centres otherwise.
    Returns:
        ``(R, n_uniform + n_surface)`` increasing depths. Rays without depth get their n_surface samples
        spread between near and far too.
    """
    r = depth_m.shape[0]
    dev, dt = depth_m.device, torch.float32
    n1, n2 = cfg.n_uniform, cfg.n_surface

    def bins(n: int) -> torch.Tensor:  # (R, n) positions in [0, 1)
        base = torch.arange(n, device=dev, dtype=dt)
        if stratified:
            jitter = torch.rand(r, n, device=dev, dtype=dt, generator=generator)
        else:
            jitter = torch.full((r, n), 0.5, device=dev, dtype=dt)
        return (base + jitter) / n

    z_uniform = cfg.near_m + (cfg.far_m - cfg.near_m) * bins(n1)
    if n2 == 0:
        return z_uniform
    t = bins(n2)
    valid = depth_m > 0
    lo = torch.where(valid, (depth_m - cfg.surface_range_m).clamp(min=cfg.near_m), torch.full_like(depth_m, cfg.near_m))
    hi = torch.where(valid, depth_m + cfg.surface_range_m, torch.full_like(depth_m, cfg.far_m))
    z_surface = lo[:, None] + (hi - lo)[:, None] * t
    return torch.sort(torch.cat([z_uniform, z_surface], dim=1), dim=1).values


def evaluated_samples(z: torch.Tensor, depth_m: torch.Tensor, skip_behind_m: float) -> torch.Tensor | None:
    """``(R, S)`` bool: the samples at depths ``z`` worth evaluating on rays with measured ``depth_m``
    ``(R,)``: all but those more than ``skip_behind_m`` behind a measured depth (see
    :class:`~neb_slam_core.config.SamplingConfig`). None when every sample is (``skip_behind_m`` 0)."""
    if skip_behind_m <= 0:
        return None
    return ~((depth_m > 0)[:, None] & (z > (depth_m + skip_behind_m)[:, None]))
