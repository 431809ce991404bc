"""Rendering through the block map: samples far behind the measured depth are skipped without changing
what the objective sees."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from neb_slam_core.render.rays import sample_pixels
from neb_slam_core.render.renderer import objective, query_samples, render_rays
from neb_slam_core.render.sampling import evaluated_samples, sample_depths
from neb_slam_core.scene.freeze import frozen


def test_evaluated_samples_skip_only_those_far_behind_a_measured_depth():
    z = torch.tensor([[0.5, 1.2, 1.3, 1.31, 2.0], [0.5, 1.2, 1.3, 1.31, 2.0]])
    depth = torch.tensor([1.0, 0.0])  # the second ray has no measurement: nothing to be behind
    keep = evaluated_samples(z, depth, 0.3)
    assert keep.tolist() == [[True, True, True, False, False], [True] * 5]
    assert evaluated_samples(z, depth, 0.0) is None


def test_skipping_leaves_rendering_and_objective_unchanged_where_the_map_has_the_surface(fitted_small_map):
    """On the map fitted to the small scene, the rays of a held-out view with its true pose: skipping
    samples more than 30 cm behind the measured depth evaluates about half of them, and the rendered depth
    and colour and the objective (its four ray terms) stay those of evaluating all of them."""
    fm = fitted_small_map
    frame = fm.held_out[1]
    px = sample_pixels(frame, 1024, np.random.default_rng(3), valid_depth_only=True)
    rays = px.to_world(torch.as_tensor(frame.T_world_cam, dtype=torch.float32))
    everything = replace(fm.render, sampling=replace(fm.render.sampling, skip_behind_m=0.0))
    skipping = replace(fm.render, sampling=replace(fm.render.sampling, skip_behind_m=0.3))
    z = sample_depths(px.depth_m, fm.render.sampling, generator=torch.Generator().manual_seed(4))
    with frozen(fm.block_map), torch.no_grad():
        full = render_rays(fm.block_map, rays, everything, z=z)
        part = render_rays(fm.block_map, rays, skipping, z=z)
        loss_full, _ = objective(fm.block_map, rays, everything, with_smoothness=False, z=z)
        loss_part, _ = objective(fm.block_map, rays, skipping, with_smoothness=False, z=z)
    share = float(evaluated_samples(z, px.depth_m, 0.3).float().mean())
    assert 0.3 < share < 0.8, share
    near = (full.depth_m - px.depth_m).abs() < 0.3 - fm.render.truncation_m  # the map has the surface there
    assert float(near.float().mean()) > 0.95
    torch.testing.assert_close(part.depth_m[near], full.depth_m[near], atol=1e-5, rtol=0)
    torch.testing.assert_close(part.rgb[near], full.rgb[near], atol=1e-5, rtol=0)
    part_values, full_values = loss_part.as_floats(), loss_full.as_floats()
    for term in ("colour", "depth", "sdf", "free_space"):
        assert abs(part_values[term] - full_values[term]) <= 1e-3 * full_values[term] + 1e-9, term


def test_skipped_samples_get_no_gradient_and_are_invalid(fitted_small_map):
    fm = fitted_small_map
    frame = fm.held_out[0]
    px = sample_pixels(frame, 64, np.random.default_rng(5), valid_depth_only=True)
    rays = px.to_world(torch.as_tensor(frame.T_world_cam, dtype=torch.float32))
    z = sample_depths(px.depth_m, fm.render.sampling, generator=torch.Generator().manual_seed(6))
    points = (rays.origins[:, None, :] + z[..., None] * rays.dirs[:, None, :]).requires_grad_(True)
    sampling = replace(fm.render.sampling, skip_behind_m=0.3)
    with frozen(fm.block_map):
        q = query_samples(fm.block_map, points, z, px.depth_m, sampling)
        (q.sdf.sum() + q.rgb.sum()).backward()
    skipped = ~evaluated_samples(z, px.depth_m, 0.3)
    assert bool(skipped.any())
    assert not bool(q.valid.reshape(z.shape)[skipped].any())
    assert float(q.sdf.detach().reshape(z.shape)[skipped].abs().max()) == 0.0
    assert float(points.grad[skipped].abs().max()) == 0.0
    assert float(points.grad[~skipped].abs().max()) > 0.0
