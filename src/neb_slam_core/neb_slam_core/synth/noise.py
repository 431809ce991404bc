"""A Kinect-like depth noise model for synthetic depth images (off by default).

Applied to a clean rendered depth image ``z`` (metres, 0 = no measurement), in this order:

1. **Axial noise** (Nguyen, Izadi, Lovell 2012, "Modeling Kinect sensor noise for improved 3D
   reconstruction and tracking"): ``z + N(0, sigma(z)^2)`` with
   ``sigma(z) = a + b (z - z0)^2``, ``a = 0.0012 m``, ``b = 0.0019 m^-1``, ``z0 = 0.4 m``
   (1.3 mm at 0.5 m, 6.1 mm at 2 m, 2.3 cm at 4 m).
2. **Disparity quantisation**: a structured-light sensor measures disparity, so depth comes in steps
   that grow with ``z^2``: ``1/z`` is rounded to a multiple of ``disparity_step_per_m``
   (2.85e-3 1/m: steps of 2.9 mm at 1 m and 7 cm at 5 m, Khoshelham & Elberink 2012). 0 disables it.
3. **Dropout at depth edges**: a pixel whose clean depth differs from a valid 4-neighbour by more than
   ``edge_jump_rel * z`` is lost with probability ``edge_dropout_prob`` (mixed pixels at silhouettes).
4. **Dropout at grazing angles**: with incidence angle ``theta`` between the viewing ray and the
   surface normal, a pixel is lost with probability rising linearly from 0 at ``grazing_start_deg``
   to 1 at ``grazing_full_deg``.
5. **Random dropout**: each remaining pixel is lost with probability ``random_dropout_prob``.

Lost pixels read 0, as a real sensor's holes do. Colour is not changed. The random draws come from the
generator passed in; the synthetic-sequence generator seeds it from the scene seed and frame index, so
noisy sequences are reproducible too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError


@dataclass(frozen=True)
class DepthNoiseSpec:
    """Parameters of the depth noise model (see the module docstring); ``enabled`` switches it on."""

    enabled: bool = False
    axial_a_m: float = 0.0012
    axial_b_per_m: float = 0.0019
    axial_z0_m: float = 0.4
    disparity_step_per_m: float = 2.85e-3
    edge_jump_rel: float = 0.05
    edge_dropout_prob: float = 0.5
    grazing_start_deg: float = 70.0
    grazing_full_deg: float = 85.0
    random_dropout_prob: float = 0.002

    def validate(self) -> None:
        for name in ("edge_dropout_prob", "random_dropout_prob"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"DepthNoiseSpec.{name}: expected a probability in [0, 1], got {p}")
        if not 0.0 <= self.grazing_start_deg < self.grazing_full_deg <= 90.0:
            raise ConfigError(
                "DepthNoiseSpec: expected 0 <= grazing_start_deg < grazing_full_deg <= 90, got "
                f"{self.grazing_start_deg}, {self.grazing_full_deg}"
            )
        if self.axial_a_m < 0 or self.axial_b_per_m < 0 or self.disparity_step_per_m < 0:
            raise ConfigError("DepthNoiseSpec: noise magnitudes must be >= 0")


def axial_sigma_m(depth_m: np.ndarray, spec: DepthNoiseSpec) -> np.ndarray:
    """Standard deviation of the axial noise at depth ``depth_m`` (any shape), metres."""
    z = np.asarray(depth_m, dtype=np.float64)
    return spec.axial_a_m + spec.axial_b_per_m * (z - spec.axial_z0_m) ** 2


def quantize_depth(depth_m: np.ndarray, disparity_step_per_m: float) -> np.ndarray:
    """Round ``1 / z`` to a multiple of ``disparity_step_per_m`` (0 stays 0); float64 result."""
    z = np.asarray(depth_m, dtype=np.float64)
    if disparity_step_per_m <= 0:
        return z.copy()
    out = np.zeros_like(z)
    valid = z > 0
    k = np.maximum(np.round(1.0 / (z[valid] * disparity_step_per_m)), 1.0)
    out[valid] = 1.0 / (k * disparity_step_per_m)
    return out


def depth_edges(depth_m: np.ndarray, jump_rel: float) -> np.ndarray:
    """``(H, W)`` bool: valid pixels whose depth differs from a valid 4-neighbour by > ``jump_rel * z``."""
    z = np.asarray(depth_m, dtype=np.float64)
    edge = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a = np.take(z, np.arange(z.shape[axis] - 1), axis=axis)
        b = np.take(z, np.arange(1, z.shape[axis]), axis=axis)
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > jump_rel * np.minimum(a, b))
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        edge[tuple(lo)] |= jump
        edge[tuple(hi)] |= jump
    return edge


def apply_depth_noise(
    depth_m: np.ndarray, cos_incidence: np.ndarray, spec: DepthNoiseSpec, rng: np.random.Generator
) -> np.ndarray:
    """The model above applied to a clean depth image.

    Args:
        depth_m: ``(H, W)`` float32 clean depth, 0 = no measurement.
        cos_incidence: ``(H, W)`` cosine of the angle between the viewing ray and the surface normal.
        spec: the model's parameters (``spec.enabled`` is not consulted: the caller decides).
        rng: the source of randomness.

    Returns:
        ``(H, W)`` float32 noisy depth, 0 where lost.
    """
    spec.validate()
    z = np.asarray(depth_m, dtype=np.float64)
    valid = z > 0
    noisy = z + rng.standard_normal(z.shape) * axial_sigma_m(z, spec)
    noisy = np.where(valid & (noisy > 0), noisy, 0.0)
    noisy = quantize_depth(noisy, spec.disparity_step_per_m)

    u = rng.random((3,) + z.shape)
    lost = depth_edges(z, spec.edge_jump_rel) & (u[0] < spec.edge_dropout_prob)
    theta = np.degrees(np.arccos(np.clip(np.abs(cos_incidence), 0.0, 1.0)))
    p_grazing = np.clip((theta - spec.grazing_start_deg) / (spec.grazing_full_deg - spec.grazing_start_deg), 0.0, 1.0)
    lost |= u[1] < p_grazing
    lost |= u[2] < spec.random_dropout_prob
    noisy[lost | ~valid] = 0.0
    return noisy.astype(np.float32)
