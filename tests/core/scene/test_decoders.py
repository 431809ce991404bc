"""The decoders' C++ forward (no-gradient queries) against the torch modules it replaces there."""

import pytest
import torch

from neb_slam_core.config import DecoderConfig
from neb_slam_core.errors import ConfigError
from neb_slam_core.scene.decoders import Decoders


def _pair(n_blob: int, n_grid: int, cfg: DecoderConfig, dtype=torch.float32, seed: int = 0):
    """Fast and reference decoders with the same weights, drawn larger than nn.Linear's initialisation so
    that every unit's ReLU is on for some inputs and off for others and the colours are not all ~0.5."""
    torch.manual_seed(seed)
    ref = Decoders(n_blob, n_grid, cfg, backend="reference").to(dtype)
    with torch.no_grad():
        for p in ref.parameters():
            p.normal_(0.0, 0.25)
    fast = Decoders(n_blob, n_grid, cfg, backend="fast").to(dtype)
    fast.load_state_dict(ref.state_dict())
    return fast, ref


def _inputs(n: int, n_blob: int, n_grid: int, dtype, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, n_blob, generator=g, dtype=dtype), torch.randn(n, n_grid, generator=g, dtype=dtype)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("n", [1, 63, 64, 1000, 4097])  # short, exact and ragged last blocks of 64 points
def test_fast_forward_matches_the_torch_modules(fast_ext, dtype, tol, n):
    fast, ref = _pair(48, 32, DecoderConfig(), dtype)
    blob, feats = _inputs(n, 48, 32, dtype)
    with torch.no_grad():
        assert fast.uses_fast_path(blob, feats) and not ref.uses_fast_path(blob, feats)
        sdf_f, rgb_f = fast(blob, feats)
        sdf_r, rgb_r = ref(blob, feats)
        sdf_only = fast.sdf_only(blob, feats)
    assert sdf_f.shape == (n,) and rgb_f.shape == (n, 3) and sdf_f.dtype == dtype
    scale = float(sdf_r.abs().max()) + 1.0
    assert (sdf_f - sdf_r).abs().max() <= tol * scale
    assert (rgb_f - rgb_r).abs().max() <= tol
    assert torch.equal(sdf_only, sdf_f)
    if n >= 1000:  # inputs that exercise it: both signs of the sdf, colours spread over (0, 1)
        assert float(rgb_r.std()) > 0.05 and 0.2 < float((sdf_r > 0).float().mean()) < 0.8


def test_fast_forward_with_other_sizes(fast_ext):
    cfg = DecoderConfig(hidden_dim=16, feature_dim=7)
    fast, ref = _pair(30, 8, cfg, torch.float64, seed=2)
    blob, feats = _inputs(333, 30, 8, torch.float64)
    with torch.no_grad():
        for a, b in zip(fast(blob, feats), ref(blob, feats)):
            assert (a - b).abs().max() <= 1e-12


def test_no_points(fast_ext):
    fast, _ = _pair(48, 32, DecoderConfig())
    blob, feats = _inputs(0, 48, 32, torch.float32)
    with torch.no_grad():
        sdf, rgb = fast(blob, feats)
    assert sdf.shape == (0,) and rgb.shape == (0, 3)


def test_a_wanted_gradient_takes_the_torch_modules(fast_ext):
    fast, ref = _pair(48, 32, DecoderConfig())
    blob, feats = _inputs(100, 48, 32, torch.float32)
    feats.requires_grad_(True)
    assert not fast.uses_fast_path(blob, feats)  # grad mode is on
    sdf, rgb = fast(blob, feats)
    (sdf.sum() + rgb.sum()).backward()
    assert feats.grad is not None and float(feats.grad.abs().sum()) > 0
    assert fast.geometry[0].weight.grad is not None


def test_wrong_input_width_is_refused(fast_ext):
    fast, _ = _pair(48, 32, DecoderConfig())
    blob, feats = _inputs(10, 48, 16, torch.float32)
    with torch.no_grad(), pytest.raises(ValueError, match="do not make the geometry MLP's 80 inputs"):
        fast(blob, feats)
    blob, feats = _inputs(10, 40, 40, torch.float32)  # the right sum, split wrongly for the colour MLP
    with torch.no_grad(), pytest.raises(ValueError, match="the colour MLP's 63"):
        fast(blob, feats)


def test_unknown_backend_is_refused():
    with pytest.raises(ConfigError, match="Decoders backend 'gpu'"):
        Decoders(48, 32, backend="gpu")


def test_torch_path_equals_the_mlps_on_the_concatenated_inputs_with_gradients():
    """The torch path applies each first layer's two weight blocks to the one-blob code and the other input
    separately; that is the modules on the concatenation, values and every gradient (float64)."""
    torch.manual_seed(0)
    dec = Decoders(48, 32, DecoderConfig(), backend="reference").double()
    with torch.no_grad():
        for p in dec.parameters():
            p.normal_(0.0, 0.25)
    blob, feats = _inputs(300, 48, 32, torch.float64)
    blob.requires_grad_(True)
    feats.requires_grad_(True)

    def by_concatenation():
        h = dec.geometry(torch.cat([blob, feats], dim=-1))
        return h[:, 0], torch.sigmoid(dec.colour(torch.cat([blob, h[:, 1:]], dim=-1)))

    results = []
    for fn in (lambda: dec(blob, feats), by_concatenation):
        sdf, rgb = fn()
        loss = (sdf * torch.linspace(-1, 1, 300, dtype=torch.float64)).sum() + (rgb**2).sum()
        grads = torch.autograd.grad(loss, [blob, feats, *dec.parameters()])
        results.append((sdf.detach(), rgb.detach(), grads))
    (sdf, rgb, grads), (sdf_ref, rgb_ref, grads_ref) = results
    torch.testing.assert_close(sdf, sdf_ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(rgb, rgb_ref, rtol=0, atol=1e-12)
    for g, g_ref in zip(grads, grads_ref):
        torch.testing.assert_close(g, g_ref, rtol=0, atol=1e-11)
    assert 0.2 < float((sdf_ref > 0).double().mean()) < 0.8  # the ReLUs and signs are exercised
    torch.testing.assert_close(dec.sdf_only(blob, feats), sdf_ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 5e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("n", [1, 64, 1000])
def test_forward_with_tangents_are_autograds_jacobian_vector_products(fast_ext, dtype, tol, n):
    # The C++ kernel and the torch maths against autograd's Jacobian-vector products of the torch modules,
    # axis by axis; the blob's tangent along axis a is its slopes in block a of the codes and 0 elsewhere.
    fast, ref = _pair(48, 32, DecoderConfig(), dtype)
    blob, feats = _inputs(n, 48, 32, dtype)
    g = torch.Generator().manual_seed(3)
    slopes, d_feats = torch.randn(n, 3, 16, generator=g, dtype=dtype), torch.randn(n, 3, 32, generator=g, dtype=dtype)
    expected = []
    for a in range(3):
        d_blob = torch.zeros(n, 48, dtype=dtype)
        d_blob[:, 16 * a : 16 * (a + 1)] = slopes[:, a]
        (sdf, rgb), (d_sdf, d_rgb) = torch.autograd.functional.jvp(
            lambda b, f: ref(b, f), (blob, feats), (d_blob, d_feats[:, a])
        )
        expected.append([t.detach() for t in (sdf, rgb, d_sdf, d_rgb)])
    for decoders in (fast, ref):
        with torch.no_grad():
            assert decoders.uses_fast_path(blob, feats) == (decoders is fast)
        sdf, rgb, d_sdf, d_rgb = decoders.forward_with_tangents(blob, feats, slopes, d_feats)
        assert d_sdf.shape == (n, 3) and d_rgb.shape == (n, 3, 3)
        scale = float(expected[0][2].abs().max()) + 1.0
        torch.testing.assert_close(sdf, expected[0][0], rtol=0, atol=tol * scale)
        torch.testing.assert_close(rgb, expected[0][1], rtol=0, atol=tol)
        for a in range(3):
            torch.testing.assert_close(d_sdf[:, a], expected[a][2], rtol=0, atol=tol * scale)
            torch.testing.assert_close(d_rgb[:, a], expected[a][3], rtol=0, atol=tol * scale)


def test_forward_with_tangents_refuses_mismatched_tangents(fast_ext):
    fast, _ = _pair(48, 32, DecoderConfig())
    blob, feats = _inputs(5, 48, 32, torch.float32)
    with pytest.raises(ValueError, match=r"tangents \(5, 3, 48\)"):
        fast.forward_with_tangents(blob, feats, torch.zeros(5, 3, 48), torch.zeros(5, 3, 32))
