import math

import torch

from neb_slam_core.config import SamplingConfig
from neb_slam_core.render.sampling import sample_depths
from neb_slam_core.render.volume import composite, sdf_weights


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
    zu = sample_depths(torch.zeros(1), SamplingConfig(n_uniform=4, n_surface=0, near_m=0.0, far_m=4.0), stratified=False)
    assert torch.allclose(zu, torch.tensor([[0.5, 1.5, 2.5, 3.5]]))
