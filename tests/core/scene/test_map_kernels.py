"""The map's C++ kernels as a module: the one built at install is the one loaded, every function checks its
tensors itself (a RuntimeError naming the function and the argument), and the first-use build, the
fallback, compiles into a private folder and keeps its binary under its build key.

What the kernels compute is tested against the plain-torch references in test_hash_grid.py,
test_one_blob.py, test_decoders.py and test_block_map.py.
"""

from __future__ import annotations

import logging
import re
import types
from pathlib import Path

import pytest
import torch

from neb_slam_core.config import DecoderConfig, HashGridConfig
from neb_slam_core.scene import _ext
from neb_slam_core.scene.decoders import Decoders
from neb_slam_core.scene.hash_grid import HashGrid

REINSTALL = ".venv/bin/python -m pip install --no-build-isolation --no-deps -e src/neb_slam_core"


@pytest.fixture
def kernels(fast_ext):
    return fast_ext


def test_the_module_built_at_install_is_the_one_loaded(kernels):
    key = _ext.build_key(_ext.compile_flags())
    assert _ext.loaded_from_install(kernels), (
        f"loaded {kernels.__name__} ({getattr(kernels, '__file__', '?')}), the first-use build, not "
        f"{_ext.INSTALLED}: the install did not build it, or built it from other sources (rebuild: {REINSTALL})"
    )
    assert kernels.__name__ == "neb_slam_core.scene._map_kernels"
    assert Path(kernels.__file__).parent == Path(_ext.__file__).parent  # beside _ext.py, not in a cache
    assert kernels.build_key == key


# ---------------------------------------------------------------------------------------------- checks


def _grid_args(n: int = 6) -> tuple[dict, int]:
    """A small grid's arguments (3 levels x 2 features) for n points, and its output width."""
    grid = HashGrid(HashGridConfig(n_levels=3, log2_hashmap_size=6, base_resolution=2, max_resolution=8), seed=0)
    layout = dict(
        offsets=grid.level_offsets,
        resolutions=grid.level_resolutions,
        dense=grid.level_is_dense,
        table_size=grid.meta.table_size,
    )
    return dict(x=torch.rand(n, 3), table=grid.table.detach(), **layout), grid.n_output_dims


def _decoder_weights() -> list[torch.Tensor]:
    """W1 (16, 20), b1, W2 (6, 16), b2, W3 (16, 17), b3, W4 (3, 16), b4: 12 codes, 8 features."""
    return Decoders(12, 8, DecoderConfig(hidden_dim=16, feature_dim=5))._weights()


def _calls() -> dict:
    """Each binding function with valid arguments (float32, 6 points): name -> (kwargs, tensor args in order
    of checking)."""
    grid, d = _grid_args()
    n = grid["x"].shape[0]
    layout = {k: grid[k] for k in ("offsets", "resolutions", "dense", "table_size")}
    weights = _decoder_weights()
    blob, feat = torch.rand(n, 12), torch.rand(n, 8)
    return {
        "hash_grid_forward": dict(x=grid["x"], table=grid["table"], **layout),
        "hash_grid_backward": dict(
            grad_out=torch.rand(n, d), x=grid["x"], table=grid["table"], **layout, need_x=True, need_table=True
        ),
        "hash_grid_forward_blocks": dict(
            xw=grid["x"],
            centres=torch.rand(2, 3),
            tables=[grid["table"], grid["table"].clone()],
            **layout,
            edge=1.0,
            blend=0.1,
            with_jacobian=True,
        ),
        "one_blob_forward": dict(x=grid["x"], n_bins=4, period=2.0),
        "one_blob_backward": dict(grad_out=torch.rand(n, 12), x=grid["x"], n_bins=4, period=2.0),
        "decoder_forward": dict(blob=blob, feat=feat, weights=weights, with_colour=True),
        "decoder_forward_tangents": dict(
            blob=blob, feat=feat, blob_slopes=torch.rand(n, 3, 4), d_feat=torch.rand(n, 3, 8), weights=weights
        ),
    }


WEIGHT_NAMES = ["W1", "b1", "W2", "b2", "W3", "b3", "W4", "b4"]
#: the first floating-point argument of each function: it sets the call's dtype
FIRST_FLOAT = {"x", "xw", "blob"}


def _tensor_args(kwargs: dict) -> list[tuple[str, str, int | None]]:
    """(display name in the error, keyword, index in a list argument) of every tensor argument."""
    out = []
    for key, value in kwargs.items():
        if isinstance(value, torch.Tensor):
            out.append((key, key, None))
        elif isinstance(value, list):
            for i in range(len(value)):
                name = f"weights[{i}] ({WEIGHT_NAMES[i]})" if key == "weights" else f"{key}[{i}]"
                out.append((name, key, i))
    return out


CASES = [(fn, name, key, index) for fn, kwargs in _calls().items() for name, key, index in _tensor_args(kwargs)]


def _with(kwargs: dict, key: str, index: int | None, change) -> dict:
    changed = dict(kwargs)
    if index is None:
        changed[key] = change(kwargs[key])
    else:
        changed[key] = [change(t) if i == index else t for i, t in enumerate(kwargs[key])]
    return changed


def _wrong_dtype(name: str, t: torch.Tensor) -> torch.Tensor:
    if t.dtype == torch.bool:
        return t.to(torch.uint8)
    if t.dtype == torch.int64:
        return t.to(torch.int32)
    return t.to(torch.int32 if name in FIRST_FLOAT else torch.float64)


def _non_contiguous(t: torch.Tensor) -> torch.Tensor:
    """The same values, shape and dtype in a strided view."""
    view = torch.stack([t, t], dim=-1)[..., 0]
    assert not view.is_contiguous() and torch.equal(view, t)
    return view


def _raises(kernels, fn: str, kwargs: dict, name: str, what: str) -> None:
    with pytest.raises(RuntimeError, match=rf"^{fn}: {re.escape(name)} must {what}"):
        getattr(kernels, fn)(**kwargs)


def test_the_valid_calls_run(kernels):
    for fn, kwargs in _calls().items():
        getattr(kernels, fn)(**kwargs)


@pytest.mark.parametrize("fn, name, key, index", CASES, ids=[f"{c[0]}-{c[1]}" for c in CASES])
def test_each_tensor_argument_is_checked(kernels, fn, name, key, index):
    kwargs = _calls()[fn]
    _raises(
        kernels,
        fn,
        _with(kwargs, key, index, lambda t: _wrong_dtype(name, t)),
        name,
        r"be (float32 or float64|[A-Z][a-z]+), got",
    )
    _raises(kernels, fn, _with(kwargs, key, index, _non_contiguous), name, "be contiguous")
    _raises(kernels, fn, _with(kwargs, key, index, lambda t: t.unsqueeze(0)), name, "have shape")
    _raises(kernels, fn, _with(kwargs, key, index, lambda t: t.to("meta")), name, "be a CPU tensor")


def test_the_errors_say_what_was_expected(kernels):
    calls = _calls()
    fwd = calls["hash_grid_forward"]
    with pytest.raises(RuntimeError, match=r"hash_grid_forward: x must have shape \(\*, 3\), got \[6, 2\]"):
        kernels.hash_grid_forward(**{**fwd, "x": torch.rand(6, 2)})
    with pytest.raises(RuntimeError, match="hash_grid_forward: table must be Float, got Double"):
        kernels.hash_grid_forward(**{**fwd, "table": fwd["table"].double()})
    with pytest.raises(RuntimeError, match="one_blob_forward: x must be float32 or float64, got Int"):
        kernels.one_blob_forward(torch.zeros(4, 3, dtype=torch.int32), 4, 2.0)
    # W3 takes the 12 codes and the geometry MLP's 5 features: (16, 17)
    with pytest.raises(
        RuntimeError,
        match=r"decoder_forward: weights\[4\] \(W3\) must have shape \(16, 17\), "
        r"got \[16, 18\]",
    ):
        w = list(calls["decoder_forward"]["weights"])
        w[4] = torch.rand(16, 18)
        kernels.decoder_forward(calls["decoder_forward"]["blob"], calls["decoder_forward"]["feat"], w, True)


def test_sizes_and_layouts_are_checked(kernels):
    calls = _calls()
    fwd = calls["hash_grid_forward"]
    with pytest.raises(RuntimeError, match="offsets must run from 0 to the table's"):
        kernels.hash_grid_forward(**{**fwd, "table": fwd["table"][:-1].contiguous()})
    with pytest.raises(RuntimeError, match="table_size must be a power of two"):
        kernels.hash_grid_forward(**{**fwd, "table_size": 48})
    with pytest.raises(RuntimeError, match="built for 2 features per level"):
        kernels.hash_grid_forward(**{**fwd, "table": torch.rand(fwd["table"].shape[0], 4)})
    with pytest.raises(RuntimeError, match=r"grad_out must have shape \(6, 6\)"):
        kernels.hash_grid_backward(**{**calls["hash_grid_backward"], "grad_out": torch.rand(6, 7)})
    blocks = calls["hash_grid_forward_blocks"]
    with pytest.raises(RuntimeError, match=r"centres must have shape \(2, 3\)"):
        kernels.hash_grid_forward_blocks(**{**blocks, "centres": torch.rand(3, 3)})
    with pytest.raises(RuntimeError, match="edge must be positive"):
        kernels.hash_grid_forward_blocks(**{**blocks, "edge": 0.0})
    with pytest.raises(RuntimeError, match="n_bins out of range"):
        kernels.one_blob_forward(**{**calls["one_blob_forward"], "n_bins": 0})
    with pytest.raises(RuntimeError, match="period must be positive"):
        kernels.one_blob_backward(**{**calls["one_blob_backward"], "period": -1.0})
    tangents = calls["decoder_forward_tangents"]
    with pytest.raises(RuntimeError, match="weights must be the 8 tensors"):
        kernels.decoder_forward(tangents["blob"], tangents["feat"], tangents["weights"][:6], False)
    with pytest.raises(RuntimeError, match=r"blob_slopes must have shape \(6, 3, 4\)"):
        kernels.decoder_forward_tangents(**{**tangents, "blob_slopes": torch.rand(6, 3, 5)})


def test_outputs_and_what_is_not_asked_for(kernels):
    calls = _calls()
    grad_x, grad_table = kernels.hash_grid_backward(**{**calls["hash_grid_backward"], "need_x": False})
    assert grad_x is None and grad_table.shape == calls["hash_grid_backward"]["table"].shape
    out, valid, jac = kernels.hash_grid_forward_blocks(**{**calls["hash_grid_forward_blocks"], "with_jacobian": False})
    assert jac is None and out.shape == (6, 6) and valid.dtype == torch.bool
    sdf, rgb = kernels.decoder_forward(**{**calls["decoder_forward"], "with_colour": False})
    assert rgb is None and sdf.shape == (6,)
    empty = kernels.one_blob_forward(torch.zeros(0, 3, dtype=torch.float64), 4, 2.0)
    assert empty.shape == (0, 12) and empty.dtype == torch.float64


# ---------------------------------------------------------------------------------------------- loading


@pytest.fixture
def fresh_loader(monkeypatch, tmp_path):
    """The loader with nothing loaded yet and its cache in tmp_path."""
    monkeypatch.setenv("NEB_SLAM_EXT_DIR", str(tmp_path))
    monkeypatch.setattr(_ext, "_module", None)
    monkeypatch.setattr(_ext, "_failure", None)
    return tmp_path


def test_a_stale_install_build_is_not_used(fresh_loader, monkeypatch, caplog):
    """A module built from other sources (or flags, torch, CPU) than those at hand: the fallback instead,
    with a warning that says to reinstall."""
    monkeypatch.setattr(_ext, "build_key", lambda flags: "0123456789abcdef")
    fallback = types.ModuleType("the fallback")
    monkeypatch.setattr(_ext, "_compile_on_first_use", lambda flags, key: fallback)
    with caplog.at_level(logging.WARNING, logger=_ext.__name__):
        assert _ext.load_map_kernels() is fallback
    assert "reinstall the package" in caplog.text and "0123456789abcdef" in caplog.text


def test_the_fallback_builds_in_a_private_folder_and_keeps_the_binary(fresh_loader, monkeypatch):
    """No install build: cpp_extension.load compiles in a fresh folder of its own (torch's ``lock`` file
    lives there, where nothing else waits on it, so a process killed mid-build never blocks the next one),
    then the binary moves into the cache under its key, where the next process imports it without a
    compile. A leftover ``lock`` in the cache changes nothing."""
    from torch.utils import cpp_extension

    monkeypatch.setattr(_ext, "INSTALLED", "neb_slam_core.scene._not_built")
    (fresh_loader / "lock").touch()  # left by an old-style build: irrelevant now
    calls = []

    def fake_load(**kwargs):
        build_dir = Path(kwargs["build_directory"])
        calls.append(kwargs)
        assert build_dir.parent == fresh_loader and not (build_dir / "lock").exists()
        (build_dir / f"{kwargs['name']}.so").write_bytes(b"binary")
        return types.ModuleType(kwargs["name"])

    monkeypatch.setattr(cpp_extension, "load", fake_load)
    key = _ext.build_key(_ext.compile_flags())
    module = _ext.load_map_kernels()
    assert module.__name__ == f"neb_map_kernels_{key}" and not _ext.loaded_from_install(module)
    assert len(calls) == 1 and calls[0]["extra_cflags"][-1] == f"-DNEB_MAP_KERNELS_BUILD_KEY={key}"
    assert not Path(calls[0]["build_directory"]).exists()  # the private folder is gone
    target = fresh_loader / f"neb_map_kernels_{key}.so"
    assert target.read_bytes() == b"binary" and module.__file__ == str(target)

    imported = []
    monkeypatch.setattr(_ext, "_import_file", lambda name, path: imported.append((name, path)) or "cached")
    monkeypatch.setattr(_ext, "_module", None)
    assert _ext.load_map_kernels() == "cached"
    assert imported == [(f"neb_map_kernels_{key}", target)] and len(calls) == 1


@pytest.mark.slow
def test_the_fallback_compiles_the_same_kernels(kernels, fresh_loader):
    """A real first-use build (about a minute): it loads, carries its key, and computes exactly what the
    install build computes."""
    flags = _ext.compile_flags()
    key = _ext.build_key(flags)
    jit = _ext._compile_on_first_use(flags, key)
    assert jit.build_key == key and (fresh_loader / f"neb_map_kernels_{key}.so").is_file()
    for fn, kwargs in _calls().items():
        a, b = getattr(kernels, fn)(**kwargs), getattr(jit, fn)(**kwargs)
        for x, y in zip(a if isinstance(a, tuple) else (a,), b if isinstance(b, tuple) else (b,), strict=True):
            assert (x is None and y is None) or torch.equal(x, y), fn
