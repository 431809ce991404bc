"""Pose parameterisation for gradient-based optimisation (torch).

A pose ``T_world_cam`` is optimised as a fixed base pose plus a 6-vector delta: a rotation vector
``omega`` applied about the camera centre (``R = exp(omega) R0``) and a translation ``t = t0 + dt``. This
keeps rotation and translation decoupled (rotating does not move the centre), which conditions the
problem well for learning-rate based optimisers.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation vectors ``(..., 3)`` -> rotation matrices ``(..., 3, 3)`` (Rodrigues; exact near 0)."""
    theta2 = (omega * omega).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    theta = torch.sqrt(theta2.clamp(min=1e-24))
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp(min=1e-24))
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = torch.zeros_like(x)
    K = torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def compose_delta(T0: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Apply deltas ``(..., 6)`` = (omega, dt) to base poses ``(..., 4, 4)``: R = exp(omega) R0, t = t0 + dt."""
    R = so3_exp(delta[..., :3]) @ T0[..., :3, :3]
    t = T0[..., :3, 3] + delta[..., 3:]
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


class PoseSet(nn.Module):
    """``N`` optimisable poses: base poses (float64 buffer) and deltas (float32 parameter).

    :meth:`matrices` gives the current float32 poses; :meth:`bake` folds the deltas into the bases (call
    it after an optimisation so the next one starts from zero deltas).
    """

    def __init__(self, poses: np.ndarray | torch.Tensor):
        super().__init__()
        base = torch.as_tensor(np.asarray(poses, dtype=np.float64)).reshape(-1, 4, 4)
        self.register_buffer("base", base)
        self.delta = nn.Parameter(torch.zeros(len(base), 6))

    def __len__(self) -> int:
        return self.base.shape[0]

    def matrices(self, index: torch.Tensor | None = None) -> torch.Tensor:
        base = self.base if index is None else self.base[index]
        delta = self.delta if index is None else self.delta[index]
        return compose_delta(base.float(), delta)

    @torch.no_grad()
    def bake(self) -> None:
        self.base.copy_(compose_delta(self.base, self.delta.double()))
        self.delta.zero_()

    def numpy(self) -> np.ndarray:
        """Current poses as float64 ``(N, 4, 4)``."""
        with torch.no_grad():
            return compose_delta(self.base, self.delta.double()).cpu().numpy()
