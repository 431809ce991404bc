import math

import pytest
import torch

from neb_slam_core.config import OneBlobConfig
from neb_slam_core.errors import ConfigError
from neb_slam_core.scene.one_blob import OneBlob


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_code_at_origin_is_hand_worked(backend):
    enc = OneBlob(OneBlobConfig(n_bins=16, period_m=10.0), backend=backend)
    code = enc(torch.zeros(1, 3)).reshape(3, 16)
    # phase 0 lies 1/32 from the centres of bins 0 and 15 (on the circle), sigma = 1/16
    expected_edge = math.exp(-0.5 * (0.5) ** 2)
    assert torch.allclose(code[:, 0], torch.full((3,), expected_edge))
    assert torch.allclose(code[:, 15], torch.full((3,), expected_edge))
    # bin 8 is half a period away: distance 15/32 -> exp(-0.5 * 7.5^2)
    assert torch.allclose(code[:, 8], torch.full((3,), math.exp(-0.5 * 7.5**2)))


def test_periodic_and_bound_free():
    enc = OneBlob(OneBlobConfig(n_bins=16, period_m=10.0))
    x = torch.tensor([[0.3, -7.2, 123.4]])
    assert torch.allclose(enc(x), enc(x + 10.0), atol=1e-4)
    assert torch.allclose(enc(x), enc(x - 20.0), atol=1e-4)
    assert enc(x).shape == (1, 48)
    assert enc.n_output_dims == 48


def test_smooth_and_differentiable_in_points():
    enc = OneBlob(OneBlobConfig())
    x = torch.tensor([[1.0, 2.0, 3.0]], requires_grad=True)
    enc(x).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # a millimetre step changes the code by a millimetre's worth, not a jump
    d = (enc(x + 1e-3) - enc(x)).abs().max()
    assert d < 0.01


# ---------------------------------------------------------------------------------------------- fast path


def _points(n: int, dtype, seed: int = 0) -> torch.Tensor:
    """Points over several periods on both sides of 0, plus the awkward ones: exact bin centres, bin
    boundaries, the half-circle point opposite a centre, 0 and multiples of the period."""
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(n, 3, generator=g, dtype=dtype) * 60.0 - 30.0
    special = torch.tensor([0.0, 10.0, -10.0, 20.0, 0.3125, 0.625, 5.3125, -4.6875, 9.999999, -1e-9], dtype=dtype)
    rows = special[torch.arange(30) % len(special)].reshape(10, 3)
    return torch.cat([p, rows])


@pytest.mark.parametrize("dtype,atol", [(torch.float32, 1e-6), (torch.float64, 1e-13)])
@pytest.mark.parametrize("n_bins,period", [(16, 10.0), (17, 7.0), (2, 3.0), (1, 5.0)])
def test_fast_path_matches_the_reference(fast_ext, dtype, atol, n_bins, period):
    cfg = OneBlobConfig(n_bins=n_bins, period_m=period)
    fast, ref = OneBlob(cfg, backend="fast"), OneBlob(cfg, backend="reference")
    p = _points(5000, dtype)
    assert fast.uses_fast_path(p) and not ref.uses_fast_path(p)
    a, b = fast(p), ref(p)
    assert a.dtype == dtype and a.shape == (len(p), 3 * n_bins)
    assert (a - b).abs().max() <= atol


@pytest.mark.parametrize("dtype,rtol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_fast_path_gradient_matches_autograd_of_the_reference(fast_ext, dtype, rtol):
    cfg = OneBlobConfig()
    fast, ref = OneBlob(cfg, backend="fast"), OneBlob(cfg, backend="reference")
    # no point on a centre or exactly opposite one: |d| and min(d, 1 - d) have no derivative there
    p = torch.rand(5000, 3, generator=torch.Generator().manual_seed(3), dtype=dtype) * 60.0 - 30.0
    w = torch.randn(len(p), 48, generator=torch.Generator().manual_seed(4), dtype=dtype)
    pa, pb = p.clone().requires_grad_(True), p.clone().requires_grad_(True)
    (fast(pa) * w).sum().backward()
    (ref(pb) * w).sum().backward()
    scale = pb.grad.abs().max()
    assert (pa.grad - pb.grad).abs().max() <= rtol * scale


def test_fast_path_passes_gradcheck(fast_ext):
    enc = OneBlob(OneBlobConfig(n_bins=16, period_m=10.0), backend="fast")
    p = torch.rand(40, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 20.0 - 10.0
    assert torch.autograd.gradcheck(enc, (p.requires_grad_(True),))


def test_fast_path_keeps_leading_dimensions_and_nan(fast_ext):
    enc = OneBlob(OneBlobConfig(), backend="fast")
    p = torch.zeros(2, 5, 3)
    p[1, 2, 0] = float("nan")
    code = enc(p)
    assert code.shape == (2, 5, 48)
    assert torch.isnan(code[1, 2, :16]).all() and torch.isfinite(code[1, 2, 16:]).all()
    assert torch.equal(code[0], code[0, :1].expand(5, 48))


def test_unknown_backend_is_refused():
    with pytest.raises(ConfigError, match="OneBlob backend 'gpu'"):
        OneBlob(OneBlobConfig(), backend="gpu")


def test_codes_with_slopes_are_the_reference_and_its_derivative():
    from neb_slam_core.scene.one_blob import encode_reference, encode_with_slopes

    cfg = OneBlobConfig()
    x = (torch.rand(500, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) - 0.5) * 40.0
    code, slopes = encode_with_slopes(x, cfg.n_bins, cfg.period_m)
    torch.testing.assert_close(code, encode_reference(x, cfg.n_bins, cfg.period_m), rtol=0, atol=1e-12)
    jac = torch.autograd.functional.jacobian(lambda p: encode_reference(p, cfg.n_bins, cfg.period_m).sum(0), x)
    # (3K, N, 3): code a*K + j depends on axis a only
    k = cfg.n_bins
    for a in range(3):
        torch.testing.assert_close(slopes[:, a], jac[a * k : (a + 1) * k, :, a].T, rtol=0, atol=1e-10)
        others = [b for b in range(3) if b != a]
        assert float(jac[a * k : (a + 1) * k][:, :, others].abs().max()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_with_slopes_gives_the_forward_codes_and_their_derivatives(dtype):
    """On the fast path the codes are bit for bit those of forward (the C++ kernel), the slopes the
    reference's derivative."""
    from neb_slam_core.scene.one_blob import encode_with_slopes

    blob = OneBlob(OneBlobConfig(), backend="fast")
    x = ((torch.rand(700, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) - 0.5) * 40.0).to(dtype)
    code, slopes = blob.with_slopes(x)
    assert torch.equal(code, blob(x))
    ref_code, ref_slopes = encode_with_slopes(x.double(), blob.cfg.n_bins, blob.cfg.period_m)
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(code.double(), ref_code, rtol=0, atol=tol)
    # slopes reach K^2 / period = 25.6 per metre: the same relative tolerance
    torch.testing.assert_close(slopes.double(), ref_slopes, rtol=0, atol=tol * 30)
