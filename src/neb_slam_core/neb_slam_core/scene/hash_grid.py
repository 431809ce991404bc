"""Multi-resolution hash encoding of one neural block (the paper's f^beta_m, section "Neural Blocks").

A block's local coordinate ``x01`` in [0, 1]^3 is encoded by L grids of increasing resolution
``R_l = floor(R_min * b^l)``, ``b = exp((ln R_max - ln R_min) / (L - 1))``. At level l the point sits at
``p = x01 * R_l`` in grid units; the 8 corners of its cell (``floor(p)`` and ``floor(p) + 1`` per axis) each
look up F learnable features, and the level's feature is their trilinear interpolation. Coarse levels whose
``(R_l + 1)^3`` vertices fit in T entries are indexed densely (``ix + iy (R+1) + iz (R+1)^2``); finer levels
share T entries through the spatial hash ``(ix * 1 xor iy * 2654435761 xor iz * 805459861) & (T - 1)``.

All levels live in ONE flat table ``(n_entries, F)`` with per-level row offsets, so the parameter count is
exact: 441,905 rows x 2 x 4 B = 3.54 MB per block at T = 2^15, 239,729 rows = 1.92 MB at T = 2^14
(see :func:`hash_grid_param_count`). The output is level-major: ``[l0 f0, l0 f1, l1 f0, ...]``.

Points outside [0, 1]^3 are the caller's business (the block map discards them), but both paths clamp
them to the cube so no lookup leaves the table; as with ``torch.clamp`` the gradient w.r.t. a clamped
coordinate is zero. On a point with x == 1 the last cell ``[R - 1, R]`` is used (weight 1 on its upper
corner), so the dense table never needs row ``R + 1``. A NaN coordinate gives NaN features.

Two interchangeable implementations:

- :func:`encode_reference`: plain torch, any device and float dtype, differentiated by autograd;
- the fast CPU path: C++/OpenMP kernels (``csrc/hash_grid_kernels.h`` in the module of :mod:`._ext`,
  built at install) with a hand-written backward that computes only the gradients that are needed: the
  table gradient for mapping, the point gradient for tracking (float32 for speed, float64 for gradcheck).

:class:`HashGrid` picks between them (``backend="auto"``: fast for CPU float tensors when the kernels
load, the reference otherwise, with one warning per process when they are unavailable).
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..config import HashGridConfig
from ..errors import ConfigError
from . import _ext

log = logging.getLogger(__name__)

#: Primes of the spatial hash (Teschner et al. 2003, as in Instant-NGP); the x prime is 1.
HASH_PRIMES = (1, 2654435761, 805459861)

#: Backends of :class:`HashGrid`.
BACKENDS = ("auto", "fast", "reference")

#: Features per level the fast path is compiled for (the paper's F = 2; other values use the reference).
FAST_FEATURE_COUNTS = (2,)

# Corner k of a cell is offset by (bit 0, bit 1, bit 2) of k, the same order as the C++ kernel.
_CORNERS = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1), (1, 1, 1))

_fallback_warned = False


@dataclass(frozen=True)
class HashGridMeta:
    """Layout of the flat table: per-level resolution, indexing mode and first row.

    Attributes:
        n_levels: L.
        n_features: F, features per level.
        table_size: T, rows of a hashed level (a power of two).
        level_resolutions: ``R_l`` per level (L entries).
        level_is_dense: whether level l is indexed densely (L entries).
        level_offsets: first row of each level in the flat table, plus the total (L + 1 entries), so
            level l owns rows ``[level_offsets[l], level_offsets[l + 1])``.
    """

    n_levels: int
    n_features: int
    table_size: int
    level_resolutions: tuple[int, ...]
    level_is_dense: tuple[bool, ...]
    level_offsets: tuple[int, ...]

    @property
    def n_entries(self) -> int:
        """Rows of the flat table."""
        return self.level_offsets[-1]

    @property
    def n_output_dims(self) -> int:
        return self.n_levels * self.n_features

    @classmethod
    def from_config(cls, cfg: HashGridConfig) -> HashGridMeta:
        _validate(cfg)
        L, T = cfg.n_levels, cfg.table_size
        resolutions = resolutions_per_level(cfg.base_resolution, cfg.max_resolution, L)
        dense = tuple((r + 1) ** 3 <= T for r in resolutions)
        offsets = [0]
        for r, d in zip(resolutions, dense):
            offsets.append(offsets[-1] + ((r + 1) ** 3 if d else T))
        return cls(L, cfg.n_features_per_level, T, resolutions, dense, tuple(offsets))


def resolutions_per_level(base_resolution: int, max_resolution: int, n_levels: int) -> tuple[int, ...]:
    """``R_l = floor(R_min * b^l)`` with ``b = exp((ln R_max - ln R_min) / (L - 1))``; one level: ``R_min``.

    Some products are integers mathematically but land just below in floating point: for the paper's
    16 -> 250, ``b^5 = 2.5`` exactly, so ``R_5 = 40``, ``R_10 = 100`` and ``R_15 = R_max = 250``, which a naive
    evaluation gives as 39, 99 and 249. A relative tolerance of 1e-9 keeps those from dropping a whole unit.
    """
    if n_levels == 1:
        return (int(base_resolution),)
    b = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (n_levels - 1))
    return tuple(int(math.floor(base_resolution * b**level * (1.0 + 1e-9))) for level in range(n_levels))


def hash_grid_param_count(cfg: HashGridConfig) -> int:
    """Number of learnable scalars of one block's grid: table rows x F."""
    meta = HashGridMeta.from_config(cfg)
    return meta.n_entries * meta.n_features


def _validate(cfg: HashGridConfig) -> None:
    def need(ok: bool, field: str, expected: str) -> None:
        if not ok:
            raise ConfigError(f"HashGridConfig.{field} = {getattr(cfg, field)!r}: expected {expected}")

    need(isinstance(cfg.n_levels, int) and cfg.n_levels >= 1, "n_levels", "an integer >= 1")
    need(
        isinstance(cfg.n_features_per_level, int) and cfg.n_features_per_level >= 1,
        "n_features_per_level",
        "an integer >= 1",
    )
    need(
        isinstance(cfg.log2_hashmap_size, int) and 1 <= cfg.log2_hashmap_size <= 31,
        "log2_hashmap_size",
        "an integer in [1, 31]",
    )
    need(isinstance(cfg.base_resolution, int) and cfg.base_resolution >= 1, "base_resolution", "an integer >= 1")
    need(
        isinstance(cfg.max_resolution, int) and cfg.max_resolution >= cfg.base_resolution,
        "max_resolution",
        f"an integer >= base_resolution ({cfg.base_resolution})",
    )
    need(cfg.init_scale >= 0, "init_scale", "a number >= 0")


def _check_points(x01: Tensor) -> None:
    if x01.ndim < 1 or x01.shape[-1] != 3:
        raise ValueError(f"hash grid: x01 must have shape (..., 3), got {tuple(x01.shape)}")
    if not x01.is_floating_point():
        raise ValueError(f"hash grid: x01 must be a floating-point tensor, got {x01.dtype}")


# ---------------------------------------------------------------------------------------------- reference


def level_cells(x01: Tensor, meta: HashGridMeta, level: int) -> tuple[Tensor, Tensor]:
    """Corner rows and trilinear weights of ``x01`` at one level (plain torch).

    Args:
        x01: ``(N, 3)`` local coordinates (clamped to [0, 1] here).
    Returns:
        rows: ``(N, 8)`` int64 absolute rows into the flat table (corner k offset by the bits of k).
        weights: ``(N, 8)`` trilinear weights, differentiable w.r.t. ``x01``.
    """
    R = meta.level_resolutions[level]
    pos = x01.clamp(0.0, 1.0) * R  # (N, 3) grid units
    # The cell comes from a detached floor (NaN -> cell 0 so every lookup stays in the table; the NaN
    # fraction then propagates); x == 1 uses the last cell [R - 1, R].
    cell = torch.nan_to_num(torch.floor(pos.detach()), nan=0.0).clamp_(0, R - 1)
    frac = pos - cell  # (N, 3) in [0, 1], d frac / d x = R
    corners = torch.tensor(_CORNERS, device=x01.device, dtype=torch.int64)  # (8, 3)
    ijk = cell.to(torch.int64)[:, None, :] + corners  # (N, 8, 3)
    if meta.level_is_dense[level]:
        idx = ijk[..., 0] + ijk[..., 1] * (R + 1) + ijk[..., 2] * (R + 1) ** 2
    else:
        # int64 products: their low 32 bits equal the uint32 arithmetic of the usual hash; & (T - 1) keeps
        # only low bits.
        idx = (ijk[..., 0] * HASH_PRIMES[0]) ^ (ijk[..., 1] * HASH_PRIMES[1]) ^ (ijk[..., 2] * HASH_PRIMES[2])
        idx = idx & (meta.table_size - 1)
    upper = corners.to(torch.bool)  # (8, 3)
    w = torch.where(upper, frac[:, None, :], 1.0 - frac[:, None, :]).prod(dim=-1)  # (N, 8)
    return idx + meta.level_offsets[level], w


def encode_reference(table: Tensor, x01: Tensor, meta: HashGridMeta) -> Tensor:
    """Hash encoding in plain torch (any device, any float dtype), differentiable by autograd.

    Args:
        table: ``(meta.n_entries, F)`` flat feature table.
        x01: ``(N, 3)`` block-local coordinates in [0, 1]^3 (clamped).
    Returns:
        ``(N, L * F)`` features, level-major, in the promoted dtype of ``table`` and ``x01``.
    """
    _check_points(x01)
    if table.shape != (meta.n_entries, meta.n_features):
        raise ValueError(f"hash grid: table must be ({meta.n_entries}, {meta.n_features}), got {tuple(table.shape)}")
    n = x01.shape[0]
    feats = []
    for level in range(meta.n_levels):
        rows, w = level_cells(x01, meta, level)
        vals = table.index_select(0, rows.reshape(-1)).reshape(n, 8, meta.n_features)  # (N, 8, F)
        feats.append((w[..., None] * vals).sum(dim=1))  # (N, F)
    return torch.cat(feats, dim=1)


# ---------------------------------------------------------------------------------------------- fast path


#: the dtypes of the fast paths (points, tables, decoder inputs)
FAST_DTYPES = (torch.float32, torch.float64)


class _FastHashEncode(torch.autograd.Function):
    """The C++ kernels as an autograd op: gradients w.r.t. the points and the table, each only when needed.

    Inputs are checked by :meth:`HashGrid.uses_fast_path` (CPU, same float dtype) and again by the kernels
    (dtypes, shapes, the level buffers against the table); here they are made contiguous.
    """

    @staticmethod
    def forward(
        ctx, x01: Tensor, table: Tensor, offsets: Tensor, resolutions: Tensor, dense: Tensor, table_size: int
    ) -> Tensor:
        kernels = _ext.load_map_kernels()
        x01 = x01.detach().contiguous()
        table_c = table.detach().contiguous()
        out = kernels.hash_grid_forward(x01, table_c, offsets, resolutions, dense, table_size)
        ctx.save_for_backward(x01, table_c, offsets, resolutions, dense)
        ctx.table_size = table_size
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):
        x01, table, offsets, resolutions, dense = ctx.saved_tensors
        need_x, need_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (need_x or need_table):
            return None, None, None, None, None, None
        grad_x, grad_table = _ext.load_map_kernels().hash_grid_backward(
            grad_out.to(x01.dtype).contiguous(),
            x01,
            table,
            offsets,
            resolutions,
            dense,
            ctx.table_size,
            need_x,
            need_table,
        )
        return grad_x, grad_table, None, None, None, None


def encode_blended(
    points_world: Tensor, centres: Tensor, grids: list[HashGrid], edge_m: float, blend_m: float, jacobian: bool = False
) -> tuple[Tensor, ...] | None:
    """Hash features of world points blended over several blocks, by the C++ kernel, without autograd.

    Block ``b`` is the cube of edge ``edge_m`` centred at ``centres[b]`` with the grid ``grids[b]``; a point
    takes the mean of the features of the blocks containing it, weighted by the blend window
    (:meth:`~neb_slam_core.scene.block_map.BlockMap.grid_features` defines it and runs the same sum in torch).

    Returns:
        ``(N, L*F)`` features and ``(N,)`` bool validity, with ``jacobian`` also ``(N, 3, L*F)``: the
        features' derivatives w.r.t. the world points (what autograd would give through the torch path;
        0 at points in no block). None when this path does not apply: a gradient is wanted (grad mode on
        and the points or a table require one), a grid runs the reference backend, the tensors are not
        on the CPU, or the grids' layouts differ. The caller then uses the torch path.
    """
    if not grids:
        return None
    x = points_world.reshape(-1, 3)
    if torch.is_grad_enabled() and (x.requires_grad or any(g.table.requires_grad for g in grids)):
        return None
    meta = grids[0].meta
    if any(g.meta != meta for g in grids) or not all(g.uses_fast_path(x) for g in grids):
        return None
    kernels = _ext.load_map_kernels()
    x = x.detach().contiguous()
    c = centres.detach().to(x.dtype).contiguous().reshape(-1, 3)
    g0 = grids[0]
    out, valid, jac = kernels.hash_grid_forward_blocks(
        x,
        c,
        [g.table.detach().contiguous() for g in grids],
        g0.level_offsets,
        g0.level_resolutions,
        g0.level_is_dense,
        meta.table_size,
        float(edge_m),
        float(blend_m),
        jacobian,
    )
    return (out, valid, jac) if jacobian else (out, valid)


#: why the fast CPU path cannot be used in this process (loads the kernels if needed), or ``None`` if it can
fast_path_unavailable_reason = _ext.unavailable_reason


def _warn_fallback(reason: str) -> None:
    global _fallback_warned
    if _fallback_warned:
        return
    _fallback_warned = True
    warnings.warn(
        f"neb_slam_core hash grid: the fast CPU path is unavailable ({reason}); using the plain-torch "
        "reference encoding instead (same results, far slower: see benchmarks/encoding.py)",
        RuntimeWarning,
        stacklevel=3,
    )


# ---------------------------------------------------------------------------------------------- module


class HashGrid(nn.Module):
    """One block's multi-resolution hash grid: ``(N, 3)`` local coordinates in [0, 1]^3 -> ``(N, L*F)``.

    Args:
        cfg: the grid's configuration (levels, features, table size, resolutions, init scale).
        backend: ``"auto"`` (fast path for CPU float32/float64 tensors when the C++ kernels load, otherwise
            the reference; unavailable kernels warn once per process), ``"fast"`` (the C++ path; raises if
            the kernels are unavailable; CPU tensors only) or ``"reference"`` (plain torch).
        seed: seed of the table's initialisation ``uniform(-init_scale, init_scale)``; ``None`` draws from
            torch's global generator.

    Attributes:
        table: ``(n_entries, F)`` float32 parameter, all levels, level l at rows
            ``level_offsets[l] : level_offsets[l + 1]``.
        level_offsets: ``(L + 1,)`` int64 buffer; level_resolutions ``(L,)`` int64; level_is_dense ``(L,)``
            bool. Non-persistent buffers (derived from the config; the state dict holds only the table).
        meta: the same layout as a :class:`HashGridMeta` (Python ints).
    """

    def __init__(self, cfg: HashGridConfig, backend: str = "auto", seed: int | None = None):
        super().__init__()
        if backend not in BACKENDS:
            raise ConfigError(f"HashGrid backend {backend!r}: expected one of {', '.join(BACKENDS)}")
        self.cfg = cfg
        self.meta = HashGridMeta.from_config(cfg)
        self.backend = backend
        generator = None if seed is None else torch.Generator().manual_seed(int(seed))
        table = torch.empty(self.meta.n_entries, self.meta.n_features, dtype=torch.float32)
        table.uniform_(-cfg.init_scale, cfg.init_scale, generator=generator)
        self.table = nn.Parameter(table)
        self.register_buffer(
            "level_offsets", torch.tensor(self.meta.level_offsets, dtype=torch.int64), persistent=False
        )
        self.register_buffer(
            "level_resolutions", torch.tensor(self.meta.level_resolutions, dtype=torch.int64), persistent=False
        )
        self.register_buffer(
            "level_is_dense", torch.tensor(self.meta.level_is_dense, dtype=torch.bool), persistent=False
        )
        if backend == "fast":
            if self.meta.n_features not in FAST_FEATURE_COUNTS:
                raise ConfigError(
                    f"HashGrid backend 'fast': n_features_per_level must be one of "
                    f"{FAST_FEATURE_COUNTS}, got {self.meta.n_features}"
                )
            reason = fast_path_unavailable_reason()
            if reason is not None:
                raise RuntimeError(f"HashGrid backend 'fast' requested but unavailable: {reason}")

    @property
    def n_output_dims(self) -> int:
        return self.meta.n_output_dims

    @property
    def n_params(self) -> int:
        return self.table.numel()

    @property
    def param_bytes(self) -> int:
        return self.table.numel() * self.table.element_size()

    def uses_fast_path(self, x01: Tensor) -> bool:
        """Whether :meth:`forward` on ``x01`` runs the C++ path (may load the kernels)."""
        if self.backend == "reference":
            return False
        eligible = (
            x01.device.type == "cpu"
            and self.table.device.type == "cpu"
            and x01.dtype in FAST_DTYPES
            and x01.dtype == self.table.dtype
            and self.meta.n_features in FAST_FEATURE_COUNTS
        )
        if self.backend == "fast":
            if not eligible:
                raise ValueError(
                    "HashGrid backend 'fast' needs CPU float32/float64 points of the table's dtype "
                    f"({self.table.dtype}, {self.table.device}); got {x01.dtype} on {x01.device}"
                )
            return True
        if not eligible:
            return False
        reason = fast_path_unavailable_reason()
        if reason is not None:
            _warn_fallback(reason)
            return False
        return True

    def forward(self, x01: Tensor) -> Tensor:
        """Encode block-local points.

        Args:
            x01: ``(..., 3)`` coordinates in [0, 1]^3 (outside: clamped, zero gradient).
        Returns:
            ``(..., L * F)`` features, level-major; differentiable w.r.t. ``table`` and ``x01``.
        """
        _check_points(x01)
        if self.table.shape != (self.meta.n_entries, self.meta.n_features):
            raise ValueError(
                f"HashGrid: table must be ({self.meta.n_entries}, {self.meta.n_features}) for this "
                f"config, got {tuple(self.table.shape)}"
            )
        lead = x01.shape[:-1]
        x = x01.reshape(-1, 3)
        if self.uses_fast_path(x):
            out = _FastHashEncode.apply(
                x, self.table, self.level_offsets, self.level_resolutions, self.level_is_dense, self.meta.table_size
            )
        else:
            out = encode_reference(self.table, x, self.meta)
        return out.reshape(*lead, self.n_output_dims)

    def extra_repr(self) -> str:
        m = self.meta
        return (
            f"levels={m.n_levels}, features={m.n_features}, T=2^{self.cfg.log2_hashmap_size}, "
            f"R={m.level_resolutions[0]}..{m.level_resolutions[-1]}, dense_levels={sum(m.level_is_dense)}, "
            f"entries={m.n_entries}, backend={self.backend}"
        )
