"""The two shared decoders of the paper (sizes from Co-SLAM, which NeB-SLAM follows).

geometry f_gamma: [one-blob (48) | hash features (32)] -> 32 -> [sdf (1) | feature g (15)]
colour   f_delta: [one-blob (48) | g (15)]             -> 32 -> rgb (3)

The SDF is predicted in units of the truncation distance (1 = free space at the band's edge); the
renderer multiplies by ``truncation_m`` where metres are needed.

When no gradient is wanted (tracking's renders and spatial differences, meshing, evaluation renders), CPU
float tensors go through a C++ kernel that runs both MLPs on small blocks of points in cache
(``csrc/decoder_kernels.h``; torch's layer-by-layer evaluation moves every layer's activations for all
points through memory). Same maths; the tests compare the two. Mapping, which needs gradients, uses the
torch modules.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..config import DecoderConfig
from ..errors import ConfigError
from . import _ext
from .hash_grid import BACKENDS, FAST_DTYPES


def _mlp(n_in: int, n_hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, n_hidden), nn.ReLU(inplace=True), nn.Linear(n_hidden, n_out))


def _first_layer(linear: nn.Linear, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``relu(linear([a | b]))`` without concatenating ``a`` and ``b``: the weight's two column blocks apply to
    each. Same result (up to rounding); the concatenated copy of every point's inputs, and in backward
    the gradient of the part that needs none (the one-blob code when no pose is optimised), are never made."""
    n_a = a.shape[-1]
    return torch.relu_(F.linear(a, linear.weight[:, :n_a], linear.bias) + F.linear(b, linear.weight[:, n_a:]))


class Decoders(nn.Module):
    """Geometry and colour MLPs shared by all blocks.

    backend: ``"auto"`` (the C++ forward when no gradient is wanted and the inputs are CPU float tensors
        of the weights' dtype, when the C++ kernels load), ``"fast"`` (the same, an error when it cannot
        run) or ``"reference"`` (torch only), as :class:`~.hash_grid.HashGrid`'s.
    """

    def __init__(self, n_blob_dims: int, n_grid_dims: int, cfg: DecoderConfig = DecoderConfig(), backend: str = "auto"):
        super().__init__()
        if backend not in BACKENDS:
            raise ConfigError(f"Decoders backend {backend!r}: expected one of {', '.join(BACKENDS)}")
        self.cfg = cfg
        self.backend = backend
        self.geometry = _mlp(n_blob_dims + n_grid_dims, cfg.hidden_dim, 1 + cfg.feature_dim)
        self.colour = _mlp(n_blob_dims + cfg.feature_dim, cfg.hidden_dim, 3)

    def forward(self, blob: torch.Tensor, grid_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``blob`` (N, 48), ``grid_features`` (N, 32) -> (sdf in truncation units (N,), rgb in [0, 1] (N, 3))."""
        if self.uses_fast_path(blob, grid_features):
            return self._fast(blob, grid_features, with_colour=True)
        h = self._geometry(blob, grid_features)
        sdf, g = h[..., 0], h[..., 1:]
        rgb = torch.sigmoid(self.colour[2](_first_layer(self.colour[0], blob, g)))
        return sdf, rgb

    def sdf_only(self, blob: torch.Tensor, grid_features: torch.Tensor) -> torch.Tensor:
        """The SDF alone (skips the colour MLP): (N,)."""
        if self.uses_fast_path(blob, grid_features):
            return self._fast(blob, grid_features, with_colour=False)[0]  # no colour computed
        return self._geometry(blob, grid_features)[..., 0]

    def forward_with_tangents(
        self, blob: torch.Tensor, grid_features: torch.Tensor, blob_slopes: torch.Tensor, d_features: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """Both MLPs and their derivatives along the three world axes (forward mode), without autograd.

        Args:
            blob: ``(N, 3K)`` one-blob codes, axis-major (block ``a`` of K codes depends on axis ``a`` alone).
            grid_features: ``(N, D)`` hash features.
            blob_slopes: ``(N, 3, K)``: entry ``[n, a, j]`` is ``d blob[n, a K + j] / d x_a`` (the codes'
                derivatives along the other axes are 0).
            d_features: ``(N, 3, D)``: the features' derivatives along each axis.
        Returns:
            sdf ``(N,)``, rgb ``(N, 3)``, their derivatives ``(N, 3)`` and ``(N, 3, 3)`` (``[n, a, c]``: along
            axis ``a``).

        Tracking's spatial gradients: a ReLU passes a tangent where its input is positive, the sigmoid scales
        it by ``rgb (1 - rgb)``. Autograd has no forward mode through the C++ encodings, and its reverse mode
        would take one backward pass per output. The C++ kernel when :meth:`uses_fast_path`
        (``csrc/decoder_kernels.h``), else the same maths in torch.
        """
        n, n_blob = blob.shape
        if (
            blob_slopes.shape != (n, 3, n_blob // 3)
            or n_blob % 3
            or d_features.shape != (grid_features.shape[0], 3, grid_features.shape[1])
        ):
            raise ValueError(
                f"Decoders: tangents {tuple(blob_slopes.shape)} and {tuple(d_features.shape)} do not "
                f"match the inputs {tuple(blob.shape)} and {tuple(grid_features.shape)} "
                "((N, 3, blob dims / 3) and (N, 3, feature dims))"
            )
        with torch.no_grad():
            if self.uses_fast_path(blob, grid_features):
                return self._fast_tangents(blob, grid_features, blob_slopes, d_features)
            d_blob = torch.zeros(n, 3, 3, n_blob // 3, dtype=blob.dtype, device=blob.device)
            for axis in range(3):  # tangent along axis a: only block a of the codes moves
                d_blob[:, axis, axis] = blob_slopes[:, axis]
            d_blob = d_blob.reshape(n, 3, n_blob)

            def first(linear: nn.Linear, a, b, da, db):
                n_a = a.shape[-1]
                w_a, w_b = linear.weight[:, :n_a], linear.weight[:, n_a:]
                z = F.linear(a, w_a, linear.bias) + F.linear(b, w_b)
                on = (z > 0).to(z.dtype)
                return z * on, (F.linear(da, w_a) + F.linear(db, w_b)) * on[:, None, :]

            geo_hidden, d_geo_hidden = first(self.geometry[0], blob, grid_features, d_blob, d_features)
            out = self.geometry[2](geo_hidden)
            d_out = F.linear(d_geo_hidden, self.geometry[2].weight)
            col_hidden, d_col_hidden = first(self.colour[0], blob, out[:, 1:], d_blob, d_out[..., 1:])
            rgb = torch.sigmoid(self.colour[2](col_hidden))
            d_rgb = F.linear(d_col_hidden, self.colour[2].weight) * (rgb * (1.0 - rgb))[:, None, :]
            return out[:, 0], rgb, d_out[..., 0], d_rgb

    def _geometry(self, blob: torch.Tensor, grid_features: torch.Tensor) -> torch.Tensor:
        return self.geometry[2](_first_layer(self.geometry[0], blob, grid_features))

    def _weights(self) -> list[torch.Tensor]:
        return [
            t.detach().contiguous()
            for layer in (self.geometry[0], self.geometry[2], self.colour[0], self.colour[2])
            for t in (layer.weight, layer.bias)
        ]

    def uses_fast_path(self, blob: torch.Tensor, grid_features: torch.Tensor) -> bool:
        """Whether a call on these inputs runs the C++ forward: no gradient wanted, CPU, the weights' float
        dtype, 2-D inputs (may load the kernels)."""
        if torch.is_grad_enabled():
            return False
        dtype = self.geometry[0].weight.dtype
        eligible = (
            dtype in FAST_DTYPES
            and blob.dtype == grid_features.dtype == dtype
            and blob.device.type == grid_features.device.type == self.geometry[0].weight.device.type == "cpu"
            and blob.dim() == grid_features.dim() == 2
        )
        return _ext.use_fast_path(
            self.backend,
            eligible,
            "Decoders",
            f"2-D CPU inputs of the weights' float dtype ({dtype}); got {blob.dtype} / "
            f"{grid_features.dtype} on {blob.device}",
        )

    def _fast_tangents(
        self, blob: torch.Tensor, grid_features: torch.Tensor, blob_slopes: torch.Tensor, d_features: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        self._check_inputs(blob, grid_features)
        return tuple(
            _ext.load_map_kernels().decoder_forward_tangents(
                blob.contiguous(),
                grid_features.contiguous(),
                blob_slopes.to(blob.dtype).contiguous(),
                d_features.to(blob.dtype).contiguous(),
                self._weights(),
            )
        )

    def _check_inputs(self, blob: torch.Tensor, feats: torch.Tensor) -> None:
        if (
            blob.shape[1] + feats.shape[1] != self.geometry[0].in_features
            or feats.shape[0] != blob.shape[0]
            or blob.shape[1] + self.cfg.feature_dim != self.colour[0].in_features
        ):
            raise ValueError(
                f"Decoders: inputs {tuple(blob.shape)} and {tuple(feats.shape)} do not make the "
                f"geometry MLP's {self.geometry[0].in_features} inputs and the colour MLP's "
                f"{self.colour[0].in_features}"
            )

    def _fast(
        self, blob: torch.Tensor, grid_features: torch.Tensor, with_colour: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        self._check_inputs(blob, grid_features)
        return _ext.load_map_kernels().decoder_forward(
            blob.contiguous(), grid_features.contiguous(), self._weights(), with_colour
        )
