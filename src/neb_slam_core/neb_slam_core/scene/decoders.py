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
from .hash_grid import BACKENDS, DTYPE_CODES


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
        of the weights' dtype, when the extension builds), ``"fast"`` (the same, an error when it cannot
        run) or ``"reference"`` (torch only), as :class:`~.hash_grid.HashGrid`'s.
    """

    def __init__(self, n_blob_dims: int, n_grid_dims: int, cfg: DecoderConfig = DecoderConfig(),
                 backend: str = "auto"):
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

    def _geometry(self, blob: torch.Tensor, grid_features: torch.Tensor) -> torch.Tensor:
        return self.geometry[2](_first_layer(self.geometry[0], blob, grid_features))

    def _weights(self) -> list[torch.Tensor]:
        return [t.detach() for layer in (self.geometry[0], self.geometry[2], self.colour[0], self.colour[2])
                for t in (layer.weight, layer.bias)]

    def uses_fast_path(self, blob: torch.Tensor, grid_features: torch.Tensor) -> bool:
        """Whether a call on these inputs runs the C++ forward: no gradient wanted, CPU, the weights' float
        dtype, 2-D inputs (may build the extension)."""
        if torch.is_grad_enabled():
            return False
        dtype = self.geometry[0].weight.dtype
        eligible = (dtype in DTYPE_CODES and blob.dtype == grid_features.dtype == dtype
                    and blob.device.type == grid_features.device.type == self.geometry[0].weight.device.type == "cpu"
                    and blob.dim() == grid_features.dim() == 2)
        return _ext.use_fast_path(self.backend, eligible, "Decoders",
                                  f"2-D CPU inputs of the weights' float dtype ({dtype}); got {blob.dtype} / "
                                  f"{grid_features.dtype} on {blob.device}")

    def _fast(self, blob: torch.Tensor, grid_features: torch.Tensor,
              with_colour: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        blob, feats = blob.contiguous(), grid_features.contiguous()
        n = blob.shape[0]
        if (blob.shape[1] + feats.shape[1] != self.geometry[0].in_features or feats.shape[0] != n
                or blob.shape[1] + self.cfg.feature_dim != self.colour[0].in_features):
            raise ValueError(f"Decoders: inputs {tuple(blob.shape)} and {tuple(feats.shape)} do not make the "
                             f"geometry MLP's {self.geometry[0].in_features} inputs and the colour MLP's "
                             f"{self.colour[0].in_features}")
        weights = [t.contiguous() for t in self._weights()]
        sdf = blob.new_empty(n)
        rgb = blob.new_empty(n, 3) if with_colour else None
        _ext.load_hash_grid_ext().decoder_forward(
            DTYPE_CODES[blob.dtype], blob.data_ptr(), feats.data_ptr(), n, blob.shape[1], feats.shape[1],
            [t.data_ptr() for t in weights], self.cfg.hidden_dim, 1 + self.cfg.feature_dim, 3,
            sdf.data_ptr(), 0 if rgb is None else rgb.data_ptr(), torch.get_num_threads())
        return sdf, rgb
