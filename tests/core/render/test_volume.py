import math

import torch

from neb_slam_core.config import SamplingConfig
from neb_slam_core.render.sampling import sample_depths
from neb_slam_core.render.volume import composite, sdf_weight_slopes, sdf_weights


def test_weights_closed_form():
    sdf = torch.tensor([[0.0, 2.0, -2.0, 50.0]])
    valid = torch.ones_like(sdf, dtype=torch.bool)
    z = torch.tensor([[1.0, 1.5, 2.0, 2.5]])  # all within tr = 1 behind the first crossing (at z = 2)
    w = sdf_weights(sdf, z, valid, truncation_m=1.0)
    raw = torch.tensor([0.25, math.exp(2) / (1 + math.exp(2)) ** 2, math.exp(2) / (1 + math.exp(2)) ** 2, 0.0])
    assert torch.allclose(w[0], raw / raw.sum(), atol=1e-6)
    assert torch.allclose(w.sum(), torch.tensor(1.0))


def test_invalid_samples_get_no_weight_and_symmetric_pair_renders_midpoint():
    sdf = torch.tensor([[0.5, -0.5, 0.0]])
    valid = torch.tensor([[True, True, False]])
    z = torch.tensor([[1.0, 1.2, 7.0]])
    w = sdf_weights(sdf, z, valid, truncation_m=0.5)
    assert torch.allclose(w, torch.tensor([[0.5, 0.5, 0.0]]))
    rgb = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    depth, colour = composite(w, z, rgb)
    assert torch.allclose(depth, torch.tensor([1.1]))
    assert torch.allclose(colour, torch.tensor([[0.5, 0.5, 0.0]]))


def test_ray_with_no_valid_sample_renders_zero():
    w = sdf_weights(torch.zeros(1, 4), torch.arange(4.0)[None], torch.zeros(1, 4, dtype=torch.bool), 0.1)
    assert torch.equal(w, torch.zeros(1, 4))


def test_sharpness_and_second_surface_dropped():
    tr = 0.1
    # normalised SDF 1 (free space at the band edge) weighs sigmoid(10) sigmoid(-10) / 0.25 of a surface sample
    w = sdf_weights(torch.tensor([[1.0, 0.0]]), torch.tensor([[1.0, 2.0]]), torch.ones(1, 2, dtype=torch.bool), tr)
    ratio = (torch.sigmoid(torch.tensor(10.0)) * torch.sigmoid(torch.tensor(-10.0))) / 0.25
    assert torch.allclose(w[0, 0] / w[0, 1], ratio)
    # two surfaces along the ray: samples beyond the first crossing + tr get no weight
    sdf = torch.tensor([[0.05, -0.05, 0.05, -0.05]])
    z = torch.tensor([[1.0, 1.05, 3.0, 3.05]])
    w = sdf_weights(sdf, z, torch.ones(1, 4, dtype=torch.bool), tr)
    assert torch.allclose(w, torch.tensor([[0.5, 0.5, 0.0, 0.0]]))


def test_weight_slopes_equal_autograd_of_the_composites():
    """``d (sum_l w_il v_il) / d sdf_ij = a_ij (v_ij - sum_l w_il v_il)`` for depth and each colour channel,
    against autograd through :func:`sdf_weights` (float64), on rays with a surface, two surfaces (the
    kept mask cuts the second), invalid samples and no valid sample."""
    g = torch.Generator().manual_seed(0)
    r, s, tr = 6, 12, 0.1
    z = torch.sort(torch.rand(r, s, generator=g, dtype=torch.float64) * 4 + 0.5, dim=1).values
    sdf = (2.0 - z) / tr + 0.3 * torch.randn(r, s, generator=g, dtype=torch.float64)
    sdf[1, 8:] = (3.5 - z[1, 8:]) / tr  # a second surface behind the first
    valid = torch.rand(r, s, generator=g) > 0.2
    valid[2] = False
    rgb = torch.rand(r, s, 3, generator=g, dtype=torch.float64)
    leaf = sdf.clone().requires_grad_(True)
    w_ref = sdf_weights(leaf, z, valid, tr)
    depth, colour = composite(w_ref, z, rgb)
    w, a = sdf_weight_slopes(sdf, z, valid, tr)
    torch.testing.assert_close(w, w_ref.detach(), rtol=0, atol=1e-15)
    for value, per_sample in [(depth, z)] + [(colour[:, k], rgb[..., k]) for k in range(3)]:
        (reference,) = torch.autograd.grad(value.sum(), leaf, retain_graph=True)
        closed = a * (per_sample - value.detach()[:, None])
        torch.testing.assert_close(closed, reference, rtol=1e-10, atol=1e-12)
    assert torch.equal(a[2], torch.zeros(s, dtype=torch.float64))
    assert a.abs().max() > 1e-3  # the comparison is not between zeros


def test_sample_depths_ranges_and_order():
    cfg = SamplingConfig(n_uniform=32, n_surface=11, near_m=0.1, far_m=6.0, surface_range_m=0.05)
    depth = torch.tensor([2.0, 0.0, 0.12])
    g = torch.Generator().manual_seed(0)
    z = sample_depths(depth, cfg, stratified=True, generator=g)
    assert z.shape == (3, 43)
    assert (z[:, 1:] >= z[:, :-1]).all()
    assert z.min() >= 0.1 and z.max() <= 6.0
    # ray 0: exactly 11 samples within +/- 5 cm of the depth plus the uniform ones that fall there
    near_surface = ((z[0] - 2.0).abs() <= 0.05).sum()
    uniform_in_band = 0.1 / (5.9 / 32)  # < 1 bin: at most one uniform sample
    assert 11 <= near_surface <= 11 + math.ceil(uniform_in_band)
    # ray 2: the band is clipped at near
    assert z[2].min() >= 0.1
    # deterministic bin centres when not stratified
    zu = sample_depths(
        torch.zeros(1), SamplingConfig(n_uniform=4, n_surface=0, near_m=0.0, far_m=4.0), stratified=False
    )
    assert torch.allclose(zu, torch.tensor([[0.5, 1.5, 2.5, 3.5]]))
