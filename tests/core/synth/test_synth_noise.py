"""The Kinect-like depth noise model: documented sigma, quantisation, dropout."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from neb_slam_core.errors import ConfigError
from neb_slam_core.synth.noise import DepthNoiseSpec, apply_depth_noise, axial_sigma_m, depth_edges, quantize_depth

AXIAL_ONLY = DepthNoiseSpec(
    enabled=True,
    disparity_step_per_m=0.0,
    edge_dropout_prob=0.0,
    grazing_start_deg=89.0,
    grazing_full_deg=90.0,
    random_dropout_prob=0.0,
)


def test_axial_sigma_formula_by_hand():
    spec = DepthNoiseSpec()
    # sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2
    assert axial_sigma_m(0.4, spec) == pytest.approx(0.0012)
    assert axial_sigma_m(2.0, spec) == pytest.approx(0.0012 + 0.0019 * 1.6**2)  # 6.064 mm
    assert axial_sigma_m(4.0, spec) == pytest.approx(0.0012 + 0.0019 * 3.6**2)  # 25.82 mm


@pytest.mark.parametrize("z", [1.0, 2.0, 4.0])
def test_axial_noise_has_the_documented_sigma(z):
    depth = np.full((400, 500), z, dtype=np.float32)
    noisy = apply_depth_noise(depth, np.ones_like(depth), AXIAL_ONLY, np.random.default_rng(0)).astype(np.float64)
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    n = depth.size
    # sample std of 200,000 normal draws is within 1% of sigma (its relative std is 1/sqrt(2n) = 0.16%);
    # the mean is within 5 standard errors; float32 storage adds < 0.3 um
    assert noisy.std() == pytest.approx(sigma, rel=0.01)
    assert abs(noisy.mean() - z) < 5 * sigma / np.sqrt(n) + 1e-6
    assert (noisy > 0).all()


def test_noise_is_reproducible_and_keeps_holes():
    depth = np.full((20, 30), 2.0, dtype=np.float32)
    depth[5, 5] = 0.0
    a = apply_depth_noise(depth, np.ones_like(depth), replace(AXIAL_ONLY), np.random.default_rng(3))
    b = apply_depth_noise(depth, np.ones_like(depth), replace(AXIAL_ONLY), np.random.default_rng(3))
    assert np.array_equal(a, b) and a[5, 5] == 0.0 and a.dtype == np.float32


def test_disparity_quantisation_steps_grow_with_z_squared():
    step = 2.85e-3
    z = np.linspace(0.5, 5.0, 20001)
    q = quantize_depth(z, step)
    # every output is 1 / (k * step) for an integer k, and the rounding error is at most half a step
    k = 1.0 / (q * step)
    assert np.allclose(k, np.round(k), atol=1e-6)
    levels = np.unique(q)
    near = np.diff(levels[(levels > 0.99) & (levels < 1.01)])
    far = np.diff(levels[(levels > 4.9) & (levels < 5.1)])
    assert near.mean() == pytest.approx(step * 1.0**2, rel=0.02)  # ~2.85 mm at 1 m
    assert far.mean() == pytest.approx(step * 5.0**2, rel=0.05)  # ~7 cm at 5 m
    assert quantize_depth(np.array([0.0]), step)[0] == 0.0


def test_edge_dropout_hits_exactly_the_discontinuity():
    depth = np.full((6, 8), 1.0, dtype=np.float32)
    depth[:, 4:] = 3.0  # a jump between columns 3 and 4
    edges = depth_edges(depth, 0.05)
    assert edges[:, 3].all() and edges[:, 4].all() and edges.sum() == 12
    spec = replace(AXIAL_ONLY, axial_a_m=0.0, axial_b_per_m=0.0, edge_dropout_prob=1.0)
    out = apply_depth_noise(depth, np.ones_like(depth), spec, np.random.default_rng(0))
    assert (out[:, 3:5] == 0).all() and np.array_equal(out[:, [0, 1, 2, 5, 6, 7]], depth[:, [0, 1, 2, 5, 6, 7]])


def test_grazing_dropout_probability_is_linear_in_the_angle():
    spec = replace(AXIAL_ONLY, axial_a_m=0.0, axial_b_per_m=0.0, grazing_start_deg=70.0, grazing_full_deg=85.0)
    depth = np.full((300, 300), 2.0, dtype=np.float32)
    for angle, p_lost in ((60.0, 0.0), (80.0, 2.0 / 3.0), (86.0, 1.0)):
        cos = np.full_like(depth, np.cos(np.radians(angle)))
        lost = (apply_depth_noise(depth, cos, spec, np.random.default_rng(1)) == 0).mean()
        assert lost == pytest.approx(p_lost, abs=0.01)  # 90,000 pixels: binomial std < 0.002


def test_random_dropout_rate():
    spec = replace(AXIAL_ONLY, axial_a_m=0.0, axial_b_per_m=0.0, random_dropout_prob=0.1)
    depth = np.full((300, 300), 2.0, dtype=np.float32)
    lost = (apply_depth_noise(depth, np.ones_like(depth), spec, np.random.default_rng(2)) == 0).mean()
    assert lost == pytest.approx(0.1, abs=0.005)


def test_bad_parameters_are_rejected():
    with pytest.raises(ConfigError, match="edge_dropout_prob"):
        apply_depth_noise(
            np.ones((2, 2), np.float32),
            np.ones((2, 2)),
            replace(AXIAL_ONLY, edge_dropout_prob=1.5),
            np.random.default_rng(0),
        )
    with pytest.raises(ConfigError, match="grazing"):
        replace(DepthNoiseSpec(), grazing_start_deg=80.0, grazing_full_deg=70.0).validate()
