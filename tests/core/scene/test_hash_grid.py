"""Multi-resolution hash encoding: layout and parameter counts, hand-worked lookups, the fast C++ path
against the plain-torch reference, gradcheck on both, gradient skipping, and the build-failure fallback.

The C++ kernels are built at install (test_map_kernels.py checks the binding and the loading); every test
that needs them goes through the ``fast_ext`` fixture (conftest.py), which fails (not skips) when they are
unavailable: the fast path is part of the product.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch.func import functional_call

from neb_slam_core.config import HashGridConfig
from neb_slam_core.errors import ConfigError
from neb_slam_core.scene import _ext
from neb_slam_core.scene import hash_grid as hg
from neb_slam_core.scene.hash_grid import HashGrid, HashGridMeta, encode_reference, hash_grid_param_count

PAPER = HashGridConfig()  # L=16, F=2, T=2^15, R 16..250
SMALL_VARIANT = HashGridConfig(log2_hashmap_size=14)


def _grid(cfg: HashGridConfig, backend: str, seed: int = 0, scale: float = 1.0, dtype=torch.float32) -> HashGrid:
    """A grid with table values of a useful size (the paper's init scale 1e-4 would hide errors)."""
    grid = HashGrid(cfg, backend=backend, seed=seed).to(dtype)
    with torch.no_grad():
        gen = torch.Generator().manual_seed(seed + 1)
        grid.table.copy_((torch.rand(grid.table.shape, generator=gen, dtype=dtype) * 2 - 1) * scale)
    return grid


# --------------------------------------------------------------------------------------------- layout


def test_paper_layout_and_parameter_counts():
    meta = HashGridMeta.from_config(PAPER)
    # R_l = floor(16 b^l), b = (250/16)^(1/15) = 15.625^(1/15): b^5 = 15.625^(1/3) = 2.5 exactly, so
    # R_5 = 40, R_10 = 16 * 6.25 = 100 and R_15 = 250, which naive floating point gives as 39, 99 and 249
    # (checked with 60-digit decimal arithmetic)
    assert meta.level_resolutions == (16, 19, 23, 27, 33, 40, 48, 57, 69, 83, 100, 120, 144, 173, 208, 250)
    # (R+1)^3 <= 2^15 = 32768 for R <= 30: levels 0-3 (4913, 8000, 13824, 21952 vertices) are dense
    assert meta.level_is_dense == (True,) * 4 + (False,) * 12
    assert meta.level_offsets[:5] == (0, 4913, 12913, 26737, 48689)
    # 4913 + 8000 + 13824 + 21952 + 12 * 32768 = 441,905 rows x 2 features x 4 B = 3.54 MB
    assert meta.n_entries == 441_905
    assert hash_grid_param_count(PAPER) == 883_810
    # T = 2^14: level 3 (21952 > 16384) is hashed too: 4913 + 8000 + 13824 + 13 * 16384 = 239,729 rows
    assert HashGridMeta.from_config(SMALL_VARIANT).n_entries == 239_729
    assert hash_grid_param_count(SMALL_VARIANT) == 479_458

    grid = HashGrid(PAPER, backend="reference", seed=0)
    assert grid.table.shape == (441_905, 2) and grid.table.dtype == torch.float32
    assert grid.n_params == 883_810
    assert grid.param_bytes == 3_535_240  # 3.54 MB per block
    assert HashGrid(SMALL_VARIANT, backend="reference", seed=0).param_bytes == 1_917_832  # 1.92 MB
    assert grid.n_output_dims == 32
    assert grid.level_offsets.tolist() == list(meta.level_offsets)
    assert grid.level_resolutions.tolist() == list(meta.level_resolutions)
    assert grid.level_is_dense.tolist() == list(meta.level_is_dense)
    assert list(grid.state_dict()) == ["table"]  # the level layout derives from the config


def test_init_is_seeded_uniform():
    cfg = HashGridConfig(n_levels=2, log2_hashmap_size=8, base_resolution=2, max_resolution=8, init_scale=0.5)
    a, b, c = (HashGrid(cfg, backend="reference", seed=s).table.detach() for s in (7, 7, 8))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.abs().max() <= 0.5 and a.abs().max() > 0.4  # 283 x 2 draws fill the range


@pytest.mark.parametrize(
    "field, value",
    [
        ("n_levels", 0),
        ("n_features_per_level", 0),
        ("log2_hashmap_size", 40),
        ("base_resolution", 0),
        ("max_resolution", 8),
        ("init_scale", -1.0),
    ],
)
def test_bad_config_is_a_config_error(field, value):
    with pytest.raises(ConfigError, match=field):
        HashGrid(HashGridConfig(**{field: value}))


def test_unknown_backend_is_a_config_error():
    with pytest.raises(ConfigError, match="backend"):
        HashGrid(PAPER, backend="gpu")


# --------------------------------------------------------------------------------------------- hand-worked


BACKENDS = ["reference", "fast"]


def _backend(request, backend):
    if backend == "fast":
        request.getfixturevalue("fast_ext")
    return backend


@pytest.mark.parametrize("backend", BACKENDS)
def test_dense_level_hand_example(request, backend):
    # one level, R = 2: 3 x 3 x 3 = 27 vertices <= T = 32, row = ix + 3 iy + 9 iz
    cfg = HashGridConfig(n_levels=1, log2_hashmap_size=5, base_resolution=2, max_resolution=2)
    grid = _grid(cfg, _backend(request, backend), dtype=torch.float64)
    table = grid.table.detach()
    assert grid.meta.level_is_dense == (True,) and grid.meta.n_entries == 27
    x = torch.tensor(
        [
            [0.5, 0.0, 1.0],  # vertex (1, 0, 2) -> row 1 + 0 + 18 = 19
            [0.0, 0.0, 0.0],  # vertex (0, 0, 0) -> row 0
            [1.0, 1.0, 1.0],  # vertex (2, 2, 2) -> row 26 (x == 1 stays inside the grid)
            [0.25, 0.25, 0.25],  # centre of cell (0, 0, 0): mean of rows 0, 1, 3, 4, 9, 10, 12, 13
            [0.6, 0.2, 0.9],  # p = (1.2, 0.4, 1.8): cell (1, 0, 1), t = (0.2, 0.4, 0.8)
            [-0.5, 1.5, 0.25],  # clamped to (0, 1, 0.25): halfway between vertices (0, 2, 0) and (0, 2, 1)
        ],
        dtype=torch.float64,
    )
    out = grid(x).detach()
    assert out.shape == (6, 2)
    torch.testing.assert_close(out[0], table[19], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[1], table[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[2], table[26], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[3], table[[0, 1, 3, 4, 9, 10, 12, 13]].mean(0), rtol=0, atol=1e-12)
    expected = torch.zeros(2, dtype=torch.float64)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                w = (0.2 if a else 0.8) * (0.4 if b else 0.6) * (0.8 if c else 0.2)
                expected += w * table[(1 + a) + 3 * (0 + b) + 9 * (1 + c)]
    torch.testing.assert_close(out[4], expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(out[5], 0.5 * (table[6] + table[15]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_hash_indices_match_the_formula(request, backend):
    # level 0: R = 8, 9^3 = 729 <= 1024 dense; level 1: R = 8 * 4 = 32, 33^3 > 1024 hashed
    cfg = HashGridConfig(n_levels=2, log2_hashmap_size=10, base_resolution=8, max_resolution=32)
    grid = HashGrid(cfg, backend=_backend(request, backend), seed=0).double()
    meta = grid.meta
    assert meta.level_resolutions == (8, 32) and meta.level_is_dense == (True, False)
    assert meta.level_offsets == (0, 729, 1753)
    with torch.no_grad():  # every row holds its own index, so a lookup at a vertex returns the row it read
        grid.table[:, 0] = torch.arange(meta.n_entries, dtype=torch.float64)
        grid.table[:, 1] = -2.0 * torch.arange(meta.n_entries, dtype=torch.float64)
    vertices = [
        (0, 0, 0),
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
        (5, 17, 30),
        (31, 31, 31),
        (32, 32, 32),
        (32, 0, 7),
        (12, 25, 3),
    ]
    x = torch.tensor(vertices, dtype=torch.float64) / 32  # exact in binary: p = x * 32 is the vertex
    out = grid(x).detach()
    for (i, j, k), row in zip(vertices, out):
        h = ((i * 1) ^ (j * 2654435761) ^ (k * 805459861)) & (1024 - 1)
        assert row[2].item() == 729 + h, (i, j, k)
        assert row[3].item() == -2.0 * (729 + h)
    # the same vertices at the dense level 0 where they are vertices of it too (multiples of 4)
    for (i, j, k), row in zip(vertices, out):
        if i % 4 == 0 and j % 4 == 0 and k % 4 == 0:
            assert row[0].item() == i // 4 + 9 * (j // 4) + 81 * (k // 4)


# --------------------------------------------------------------------------------------------- fast vs reference


def _test_points(meta: HashGridMeta, n_random: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    """Random points plus the awkward ones: 0, 1, exact cell boundaries of several levels, outside the cube."""
    gen = torch.Generator().manual_seed(seed)
    pts = [torch.rand(n_random, 3, generator=gen, dtype=dtype)]
    for R in meta.level_resolutions[::3]:
        k = torch.randint(0, R + 1, (64, 3), generator=gen)
        on_face = k.to(dtype) / R
        mixed = torch.rand(64, 3, generator=gen, dtype=dtype)
        mixed[:, 1] = on_face[:, 1]  # one coordinate on a face, the others anywhere
        pts += [on_face, mixed]
    corners = torch.tensor([[0, 0, 0], [1, 1, 1], [0, 1, 0], [1, 0, 1], [0.5, 1, 0]], dtype=dtype)
    outside = torch.tensor([[-0.25, 0.5, 0.5], [0.5, 1.25, 0.5], [1.5, -2.0, 0.3], [0.2, 0.3, 7.0]], dtype=dtype)
    return torch.cat(pts + [corners, outside])


def _fwd_bwd(grid: HashGrid, x: torch.Tensor, grad_out: torch.Tensor):
    x = x.clone().requires_grad_(True)
    out = grid(x)
    gx, gt = torch.autograd.grad(out, [x, grid.table], grad_out)
    return out.detach(), gx, gt


def _assert_close_rel(actual, expected, rel=2e-5):
    """Equal up to float32 rounding, measured against the size of the values."""
    scale = max(1.0, expected.abs().max().item())
    torch.testing.assert_close(actual, expected, rtol=0, atol=rel * scale)


@pytest.mark.parametrize("cfg", [PAPER, SMALL_VARIANT], ids=["T2^15", "T2^14"])
def test_fast_matches_reference_float32(fast_ext, cfg):
    grid_fast = _grid(cfg, "fast", seed=3)
    grid_ref = _grid(cfg, "reference", seed=3)
    assert torch.equal(grid_fast.table, grid_ref.table)
    x = _test_points(grid_fast.meta, 3000, seed=5)
    grad_out = torch.randn(x.shape[0], grid_fast.n_output_dims, generator=torch.Generator().manual_seed(9))
    out_f, gx_f, gt_f = _fwd_bwd(grid_fast, x, grad_out)
    out_r, gx_r, gt_r = _fwd_bwd(grid_ref, x, grad_out)
    assert grid_fast.uses_fast_path(x) and not grid_ref.uses_fast_path(x)
    _assert_close_rel(out_f, out_r)
    _assert_close_rel(gt_f, gt_r)
    _assert_close_rel(gx_f, gx_r)
    # the clamp: points outside the cube encode as their clamped copy and get no gradient along the cut axes
    outside = x[-4:]
    torch.testing.assert_close(out_f[-4:], grid_fast(outside.clamp(0, 1)).detach(), rtol=0, atol=0)
    assert gx_f[-4, 0] == 0 and gx_f[-3, 1] == 0 and gx_f[-2, 0] == 0 and gx_f[-2, 1] == 0 and gx_f[-1, 2] == 0
    assert (gx_f[-4, 1:] != 0).all()


def test_fast_matches_reference_float64_and_batch_shapes(fast_ext):
    cfg = HashGridConfig(n_levels=6, log2_hashmap_size=12, base_resolution=4, max_resolution=64)
    grid = _grid(cfg, "fast", seed=1, dtype=torch.float64)
    x = _test_points(grid.meta, 500, seed=2, dtype=torch.float64)
    out = grid(x)
    torch.testing.assert_close(out, encode_reference(grid.table, x, grid.meta), rtol=0, atol=1e-12)
    # (..., 3) -> (..., L*F), as (n_rays, n_samples, 3) batches come in
    rays = x[:480].reshape(16, 30, 3)
    assert grid(rays).shape == (16, 30, 12)
    torch.testing.assert_close(grid(rays).reshape(480, 12), out[:480], rtol=0, atol=0)
    # no points, no work
    for backend_grid in (grid, _grid(cfg, "reference", dtype=torch.float64)):
        empty = torch.zeros(0, 3, dtype=torch.float64, requires_grad=True)
        y = backend_grid(empty)
        assert y.shape == (0, 12)
        y.sum().backward()
        assert empty.grad.shape == (0, 3)


def test_nan_points_give_nan_features_without_reading_out_of_bounds(fast_ext):
    cfg = HashGridConfig(n_levels=4, log2_hashmap_size=10, base_resolution=4, max_resolution=32)
    for backend in BACKENDS:
        grid = _grid(cfg, backend)
        x = torch.tensor([[float("nan"), 0.5, 0.5], [0.3, 0.3, 0.3]])
        out = grid(x).detach()
        assert torch.isnan(out[0]).all() and torch.isfinite(out[1]).all()


def test_bad_points_are_rejected():
    grid = HashGrid(HashGridConfig(n_levels=2, log2_hashmap_size=8, base_resolution=2, max_resolution=4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        grid(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="floating-point"):
        grid(torch.zeros(5, 3, dtype=torch.int64))


# --------------------------------------------------------------------------------------------- gradients


GRADCHECK_CFG = HashGridConfig(
    n_levels=3, n_features_per_level=2, log2_hashmap_size=6, base_resolution=2, max_resolution=8
)  # R = 2 (dense, 27 rows), 4 and 8 (hashed, 64 rows each)


def _interior_points(meta: HashGridMeta, n: int, seed: int) -> torch.Tensor:
    """Random points at least 1e-3 cell from every cell face of every level (the encoding is only C0 there,
    so finite differences across a face would disagree with the one-sided analytic gradient)."""
    gen = torch.Generator().manual_seed(seed)
    keep = []
    while len(keep) < n:
        p = torch.rand(3, generator=gen, dtype=torch.float64)
        fr = [((p * R) - torch.floor(p * R)) for R in meta.level_resolutions]
        if all(((f > 1e-3) & (f < 1 - 1e-3)).all() for f in fr):
            keep.append(p)
    return torch.stack(keep)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck(request, backend):
    grid = _grid(GRADCHECK_CFG, _backend(request, backend), seed=4, dtype=torch.float64)
    assert grid.meta.level_is_dense == (True, False, False)
    x = _interior_points(grid.meta, 6, seed=11).requires_grad_(True)
    table = grid.table.detach().clone().requires_grad_(True)
    assert grid.uses_fast_path(x) == (backend == "fast")

    def encode(table, x):
        return functional_call(grid, {"table": table}, (x,))

    assert torch.autograd.gradcheck(encode, (table, x), eps=1e-6, atol=1e-7, rtol=1e-5)


class _RecordingExt:
    """Wraps the compiled module and records which gradients each backward call was asked for."""

    def __init__(self, ext):
        self._ext = ext
        self.calls: list[tuple[bool, bool]] = []

    def hash_grid_forward(self, *args):
        return self._ext.hash_grid_forward(*args)

    def hash_grid_backward(self, *args):
        need_x, need_table = args[-2:]
        grads = self._ext.hash_grid_backward(*args)
        assert (grads[0] is not None, grads[1] is not None) == (need_x, need_table)
        self.calls.append((need_x, need_table))
        return grads


def test_backward_computes_only_the_gradients_needed(fast_ext, monkeypatch):
    grid = _grid(PAPER, "fast", seed=6)
    x0 = _test_points(grid.meta, 2000, seed=7)
    grad_out = torch.randn(x0.shape[0], 32, generator=torch.Generator().manual_seed(8))
    _, gx_full, gt_full = _fwd_bwd(grid, x0, grad_out)

    # no atomics, fixed summation orders: the same call gives bit-identical gradients
    _, gx_again, gt_again = _fwd_bwd(grid, x0, grad_out)
    assert torch.equal(gx_again, gx_full) and torch.equal(gt_again, gt_full)

    recorder = _RecordingExt(fast_ext)
    monkeypatch.setattr(_ext, "_module", recorder)

    # mapping with fixed poses: points need no gradient
    grid.table.grad = None
    grid(x0).backward(grad_out)
    assert recorder.calls[-1] == (False, True)
    torch.testing.assert_close(grid.table.grad, gt_full, rtol=0, atol=0)

    # tracking: the table is frozen, only the points get a gradient
    grid.table.requires_grad_(False)
    x = x0.clone().requires_grad_(True)
    grid(x).backward(grad_out)
    assert recorder.calls[-1] == (True, False)
    _assert_close_rel(x.grad, gx_full, rel=1e-6)  # different summation order over levels only
    grid.table.requires_grad_(True)

    # both
    x = x0.clone().requires_grad_(True)
    grid.table.grad = None
    grid(x).backward(grad_out)
    assert recorder.calls[-1] == (True, True)
    assert len(recorder.calls) == 3


def test_double_backward_is_refused(fast_ext):
    grid = _grid(GRADCHECK_CFG, "fast")
    x = torch.rand(4, 3, requires_grad=True)
    (gx,) = torch.autograd.grad(grid(x).sum(), x, create_graph=True)
    with pytest.raises(RuntimeError):
        gx.sum().backward()


# --------------------------------------------------------------------------------------------- backends


def test_build_failure_falls_back_to_reference_with_one_warning(monkeypatch):
    def broken_build():
        raise RuntimeError("no C++ compiler (simulated)")

    monkeypatch.setattr(_ext, "_module", None)
    monkeypatch.setattr(_ext, "_failure", None)
    monkeypatch.setattr(_ext, "_build", broken_build)
    monkeypatch.setattr(hg, "_fallback_warned", False)

    cfg = HashGridConfig(n_levels=3, log2_hashmap_size=8, base_resolution=4, max_resolution=16)
    grid = _grid(cfg, "auto")
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(0))
    with pytest.warns(RuntimeWarning, match=r"unavailable \(RuntimeError: no C\+\+ compiler \(simulated\)\)"):
        out = grid(x)
    torch.testing.assert_close(out, encode_reference(grid.table, x, grid.meta), rtol=0, atol=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a second warning would raise
        grid(x)
        _grid(cfg, "auto", seed=1)(x)
    assert not grid.uses_fast_path(x)
    with pytest.raises(RuntimeError, match="simulated"):
        HashGrid(cfg, backend="fast")


def test_auto_uses_the_reference_where_the_fast_path_does_not_apply(fast_ext):
    cfg = HashGridConfig(n_levels=3, log2_hashmap_size=8, base_resolution=4, max_resolution=16)
    grid = _grid(cfg, "auto")
    x = torch.rand(10, 3)
    assert grid.uses_fast_path(x)
    assert not grid.uses_fast_path(x.double())  # table float32, points float64: the reference promotes
    out = grid(x.double())
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, grid(x).double(), rtol=0, atol=1e-6)
    four = HashGrid(
        HashGridConfig(n_levels=2, n_features_per_level=4, log2_hashmap_size=8, base_resolution=2, max_resolution=4),
        seed=0,
    )
    assert not four.uses_fast_path(x) and four(x).shape == (10, 8)
    with pytest.raises(ConfigError, match="n_features_per_level"):
        HashGrid(four.cfg, backend="fast")
    with pytest.raises(ValueError, match="fast"):
        HashGrid(cfg, backend="fast")(x.double())


def test_cuda_tensors_use_the_reference():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    cfg = HashGridConfig(n_levels=4, log2_hashmap_size=10, base_resolution=4, max_resolution=32)
    grid = _grid(cfg, "auto")
    x = torch.rand(100, 3)
    expected = encode_reference(grid.table, x, grid.meta)
    grid_cuda = grid.cuda()
    assert not grid_cuda.uses_fast_path(x.cuda())
    torch.testing.assert_close(grid_cuda(x.cuda()).cpu(), expected, rtol=0, atol=1e-6)


def test_resolutions_follow_the_paper_formula():
    # one level: R_min; otherwise floor(R_min b^l) with b = (R_max / R_min)^(1/(L-1))
    assert hg.resolutions_per_level(16, 250, 1) == (16,)
    assert hg.resolutions_per_level(2, 32, 5) == (2, 4, 8, 16, 32)
    b = math.exp((math.log(512) - math.log(16)) / 7)
    assert hg.resolutions_per_level(16, 512, 8) == tuple(math.floor(16 * b**level + 1e-9) for level in range(8))
