"""Bound-free one-blob encoding of world coordinates.

One-blob (Mueller et al., "Neural Importance Sampling") turns a scalar in [0, 1) into ``K`` bins, each
the value of a Gaussian of width 1/K centred on the bin, evaluated at the scalar. Co-SLAM applies it to
coordinates normalised by the scene bounds; an unknown scene has none, so we encode each world axis by
its phase ``x / period mod 1`` and measure the distance to a bin centre on the circle. The code is
therefore smooth everywhere and needs no bounds; it repeats every ``period_m`` metres, which the
per-block hash features disambiguate.

Two interchangeable implementations, as for the hash grid (:mod:`.hash_grid`):

- :func:`encode_reference`: plain torch, any device and float dtype, differentiated by autograd;
- the fast CPU path: one pass over the points in C++ (``csrc/one_blob_kernels.h``, in the module of
  :mod:`._ext`) with a hand-written gradient w.r.t. the points. Torch's chain of about ten element-wise
  ops over ``(N, 3, K)`` and autograd's walk back through them cost more than the decoders the code
  feeds; the kernel needs two exponentials per axis and side instead of K (see its header).

Tracking's closed-form spatial gradients also need the codes' derivatives themselves (not a gradient
summed over them): :meth:`OneBlob.with_slopes`, the codes from the same path as :meth:`OneBlob.forward`
and the slopes from them and the phase offsets (:func:`encode_with_slopes` is its plain torch form).

:class:`OneBlob` picks between them like :class:`~.hash_grid.HashGrid` (``backend="auto"``: the fast path
for CPU float32/float64 points when the C++ kernels load, the reference otherwise).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..config import OneBlobConfig
from ..errors import ConfigError
from . import _ext
from .hash_grid import BACKENDS, FAST_DTYPES


def _phase_offsets(points_world: Tensor, n_bins: int, period_m: float) -> Tensor:
    """``(N, 3, K)`` signed offsets of each axis' phase from the bin centres on the unit circle (in
    [-1/2, 1/2])."""
    centres = (torch.arange(n_bins, dtype=points_world.dtype, device=points_world.device) + 0.5) / n_bins
    phase = torch.remainder(points_world / period_m, 1.0)  # (N, 3)
    s = phase[..., None] - centres  # (N, 3, K)
    return s - torch.round(s)  # the shorter way round the circle


def _offsets_and_codes(points_world: Tensor, n_bins: int, period_m: float) -> tuple[Tensor, Tensor]:
    """The phase offsets (:func:`_phase_offsets`) and the codes they give, ``(N, 3, K)`` each."""
    s = _phase_offsets(points_world, n_bins, period_m)
    return s, torch.exp(-0.5 * (s * n_bins) ** 2)  # sigma = 1 / K


def _slopes(s: Tensor, code: Tensor, n_bins: int, period_m: float) -> Tensor:
    """``d code / d x`` of the codes ``(N, 3, K)`` at phase offsets ``s``: ``-K^2 s code / period``."""
    return (-(n_bins * n_bins) / period_m) * s * code


def encode_reference(points_world: Tensor, n_bins: int, period_m: float) -> Tensor:
    """``(N, 3)`` world points -> ``(N, 3 * n_bins)`` codes, axis-major, in plain torch."""
    return _offsets_and_codes(points_world, n_bins, period_m)[1].flatten(-2)


def encode_with_slopes(points_world: Tensor, n_bins: int, period_m: float) -> tuple[Tensor, Tensor]:
    """The codes ``(N, 3 * n_bins)`` of ``(N, 3)`` world points and their slopes ``(N, 3, n_bins)``: entry
    ``[n, a, j]`` is ``d code[n, a * n_bins + j] / d x[n, a]`` (a code depends on its own axis only), in plain
    torch: ``-K^2 s code / period`` with ``s`` the signed phase offset from the bin centre."""
    s, code = _offsets_and_codes(points_world, n_bins, period_m)
    return code.flatten(-2), _slopes(s, code, n_bins, period_m)


class _FastOneBlob(torch.autograd.Function):
    """The C++ kernels as an autograd op, differentiable in the points (first order)."""

    @staticmethod
    def forward(ctx, points: Tensor, n_bins: int, period_m: float) -> Tensor:
        x = points.detach().contiguous()
        out = _ext.load_map_kernels().one_blob_forward(x, n_bins, period_m)
        ctx.save_for_backward(x)
        ctx.n_bins, ctx.period_m = n_bins, period_m
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):
        (x,) = ctx.saved_tensors
        grad_x = _ext.load_map_kernels().one_blob_backward(
            grad_out.to(x.dtype).contiguous(), x, ctx.n_bins, ctx.period_m
        )
        return grad_x, None, None


class OneBlob(torch.nn.Module):
    """``(..., 3)`` world points (metres) -> ``(..., 3 * n_bins)`` codes in [0, 1], differentiable in the points.

    backend: ``"auto"``, ``"fast"`` (the C++ path, an error when it cannot run) or ``"reference"``, as
        :class:`~.hash_grid.HashGrid`'s (the block map passes its ``grid_backend``).
    """

    def __init__(self, cfg: OneBlobConfig = OneBlobConfig(), backend: str = "auto"):
        super().__init__()
        if backend not in BACKENDS:
            raise ConfigError(f"OneBlob backend {backend!r}: expected one of {', '.join(BACKENDS)}")
        self.cfg = cfg
        self.backend = backend

    @property
    def n_output_dims(self) -> int:
        return 3 * self.cfg.n_bins

    def uses_fast_path(self, points: Tensor) -> bool:
        """Whether :meth:`forward` on ``points`` runs the C++ path (may load the kernels)."""
        eligible = points.device.type == "cpu" and points.dtype in FAST_DTYPES
        return _ext.use_fast_path(
            self.backend, eligible, "OneBlob", f"CPU float32/float64 points; got {points.dtype} on {points.device}"
        )

    def with_slopes(self, points_world: Tensor) -> tuple[Tensor, Tensor]:
        """``(N, 3)`` points -> codes ``(N, 3K)`` and slopes ``(N, 3, K)`` (:func:`encode_with_slopes`), without
        autograd. On the fast path the codes are the C++ kernel's, those of :meth:`forward`: one pass, and
        the same bits in every process, which torch's vectorised ``exp`` on the CPU does not guarantee (it
        can differ on one thread's share of a call), so a lockstep replay computes the offline run."""
        n_bins, period = self.cfg.n_bins, float(self.cfg.period_m)
        x = points_world.reshape(-1, 3)
        if not self.uses_fast_path(x):
            return encode_with_slopes(x, n_bins, period)
        with torch.no_grad():
            x = x.detach().contiguous()
            code = _ext.load_map_kernels().one_blob_forward(x, n_bins, period)
            return code, _slopes(_phase_offsets(x, n_bins, period), code.view(-1, 3, n_bins), n_bins, period)

    def forward(self, points_world: Tensor) -> Tensor:
        lead = points_world.shape[:-1]
        x = points_world.reshape(-1, 3)
        if self.uses_fast_path(x):
            code = _FastOneBlob.apply(x, self.cfg.n_bins, float(self.cfg.period_m))
        else:
            code = encode_reference(x, self.cfg.n_bins, self.cfg.period_m)
        return code.reshape(*lead, self.n_output_dims)
