import pytest
import torch

from neb_slam_core.config import LossWeights
from neb_slam_core.render.losses import (
    KINECT_DEPTH_NOISE,
    Residual,
    combine,
    depth_noise_weights,
    render_residuals,
    smoothness_residual,
)

W = LossWeights(colour=5, depth=0.1, sdf=1000, free_space=10, smoothness=1e-6)


def _terms(rgb, rgb_obs, observed, depth, depth_obs, sdf=None, z=None, valid=None, tr=0.1):
    r = rgb.shape[0]
    if sdf is None:
        sdf, z, valid = torch.zeros(r, 1), torch.ones(r, 1), torch.zeros(r, 1, dtype=torch.bool)
    return render_residuals(W, tr, rgb, depth, sdf, z, valid, observed, rgb_obs, depth_obs)


def test_colour_and_depth_terms_hand_worked():
    pred = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    obs = torch.tensor([[0.5, 0.5, 0.8], [1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    observed = torch.tensor([True, True, False])  # the third ray had no valid sample
    t = _terms(pred, obs, observed, torch.zeros(3), torch.ones(3))
    assert torch.isclose(t["colour"].value(), torch.tensor((0.09 / 3 + 0.0) / 2))
    d_pred = torch.tensor([1.0, 2.0, 3.0, 4.0])
    d_obs = torch.tensor([1.1, 0.0, 2.8, 9.0])  # ray 1 has no depth; ray 3 is not observed
    t = _terms(torch.zeros(4, 3), torch.zeros(4, 3), torch.tensor([True, True, True, False]), d_pred, d_obs)
    assert torch.isclose(t["depth"].value(), torch.tensor((0.01 + 0.04) / 2))


def test_sdf_and_free_space_hand_worked():
    tr = 0.1
    z = torch.tensor([[1.0, 1.95, 2.05, 2.5], [0.5, 1.0, 1.5, 2.0]])
    depth = torch.tensor([2.0, 0.0])  # the second ray has no depth: ignored
    valid = torch.ones(2, 4, dtype=torch.bool)
    rays = (torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2, dtype=torch.bool), torch.zeros(2), depth)

    def sdf_terms(sdf):
        t = _terms(*rays, sdf=sdf, z=z, valid=valid, tr=tr)
        return t["sdf"].value(), t["free_space"].value()

    # perfect prediction: free space 1 (= tr), band sdf = (d - z) / tr
    l_sdf, l_fs = sdf_terms(torch.tensor([[1.0, 0.5, -0.5, -3.0], [9.0, 9.0, 9.0, 9.0]]))
    assert torch.isclose(l_sdf, torch.tensor(0.0), atol=1e-12) and torch.isclose(l_fs, torch.tensor(0.0))
    # errors: free-space sample predicts 0.5 (-> (0.5-1)^2); band samples off by 1 cm and 3 cm; the sample
    # 50 cm behind the surface is unconstrained
    sdf = torch.tensor([[0.5, 0.6, -0.2, 7.0], [9.0, 9.0, 9.0, 9.0]])
    l_sdf, l_fs = sdf_terms(sdf)
    assert torch.isclose(l_fs, torch.tensor(0.25))
    assert torch.isclose(l_sdf, torch.tensor((0.01**2 + 0.03**2) / 2), atol=1e-9)
    # invalid samples do not count
    valid[0, 1] = False
    l_sdf, _ = sdf_terms(sdf)
    assert torch.isclose(l_sdf, torch.tensor(0.03**2), atol=1e-9)


def test_smoothness_sums_per_point_and_averages_over_valid_points():
    f = torch.zeros(2, 4)
    nb = torch.ones(2, 3, 4)
    nb[1] *= 2
    term = smoothness_residual(1e-6, f, nb, torch.tensor([True, False]))
    assert torch.isclose(term.value(), torch.tensor(12.0))  # 3 neighbours x 4 features x 1^2
    assert term.source is None


def test_weighted_total_in_the_terms_order():
    ones = {
        name: Residual(torch.ones(1, 1), torch.ones(1, 1, dtype=torch.bool), w, "depth")
        for name, w in (("colour", 5), ("depth", 0.1), ("sdf", 1000), ("free_space", 10), ("smoothness", 1e-6))
    }
    t = combine(ones)
    assert torch.isclose(t.total, torch.tensor(5 + 0.1 + 1000 + 10 + 1e-6))
    assert set(t.as_floats()) == {"colour", "depth", "sdf", "free_space", "smoothness", "total"}
    with pytest.raises(ValueError):
        combine({})


@pytest.mark.parametrize("row_weighted", [False, True], ids=["rows-alike", "row-weights"])
@pytest.mark.parametrize("per_row", ["mean", "sum"])
def test_entry_weights_give_the_weighted_loss(per_row, row_weighted):
    """What Gauss-Newton sums, ``sum(w r^2)``, is the weight times the loss Adam differentiates, with and
    without a weight per row."""
    g = torch.Generator().manual_seed(0)
    r = torch.randn(7, 5, generator=g)
    mask = torch.rand(7, 5, generator=g) > 0.4
    mask[3] = False  # a row without entries: not in the mean over rows
    row_w = torch.rand(7, generator=g) * 3 if row_weighted else torch.ones(7)
    term = Residual(r, mask, 2.5, "sdf", per_row=per_row, row_weight=row_w if row_weighted else None)
    w = term.entry_weights()
    assert torch.isclose((w * r * r).sum(), 2.5 * term.value(), rtol=1e-6)
    assert bool((w[~mask] == 0).all())
    # by hand for row 0: mean (or sum) of its masked squares times its weight, then the mean over the 6
    # rows with entries
    rows = [
        row_w[i] * ((r[i][mask[i]] ** 2).mean() if per_row == "mean" else (r[i][mask[i]] ** 2).sum())
        for i in range(7)
        if mask[i].any()
    ]
    assert torch.isclose(term.value(), torch.stack(rows).mean(), rtol=1e-6)


def test_depth_noise_weights_follow_the_inverse_variance_and_average_one():
    a, b, c = KINECT_DEPTH_NOISE
    assert (a, b, c) == (0.0012, 0.0019, 0.4)
    depth = torch.tensor([0.4, 2.4, 0.0, 1.4], dtype=torch.float64)
    w = depth_noise_weights(depth)
    # sigma: 1.2 mm at 0.4 m, 1.2 + 1.9 * 4 = 8.8 mm at 2.4 m, 1.2 + 1.9 = 3.1 mm at 1.4 m
    inv = torch.tensor([1 / 1.2**2, 1 / 8.8**2, 0.0, 1 / 3.1**2], dtype=torch.float64)
    torch.testing.assert_close(w, inv * 3 / inv.sum())
    assert float(w[2]) == 0.0 and float(w[[0, 1, 3]].mean()) == pytest.approx(1.0)
    assert float(w[0] / w[1]) == pytest.approx((8.8 / 1.2) ** 2)
    assert bool((depth_noise_weights(torch.zeros(3)) == 0).all())  # no depth: no weight, no division by 0


def test_depth_noise_weighs_the_geometry_terms_of_each_ray_and_leaves_colour_alone():
    """Two rays, 1 m away and 1 cm off in rendered depth, 3 m away and 3 cm off: sigma 1.2 + 1.9 * 0.6^2 =
    1.884 mm and 1.2 + 1.9 * 2.6^2 = 14.044 mm, so the near ray weighs (14.044 / 1.884)^2 = 55.6 times the
    far one, the weights 2 * 55.6 / 56.6 and 2 / 56.6 (mean 1); the depth loss drops from the plain mean
    (1 + 9) / 2 cm^2 to (1.965 * 1 + 0.0353 * 9) / 2 cm^2."""
    rgb, rgb_obs = torch.zeros(2, 3), torch.tensor([[0.1, 0.0, 0.0], [0.3, 0.0, 0.0]])
    observed = torch.ones(2, dtype=torch.bool)
    depth_obs = torch.tensor([1.0, 3.0], dtype=torch.float64)
    depth = depth_obs + torch.tensor([0.01, 0.03], dtype=torch.float64)
    sdf, z, valid = torch.zeros(2, 1), torch.ones(2, 1), torch.zeros(2, 1, dtype=torch.bool)
    plain = render_residuals(W, 0.1, rgb, depth, sdf, z, valid, observed, rgb_obs, depth_obs)
    weighted = render_residuals(W, 0.1, rgb, depth, sdf, z, valid, observed, rgb_obs, depth_obs, depth_noise=True)
    ratio = (14.044 / 1.884) ** 2
    near, far = 2 * ratio / (1 + ratio), 2 / (1 + ratio)
    torch.testing.assert_close(depth_noise_weights(depth_obs), torch.tensor([near, far], dtype=torch.float64))
    assert float(plain["depth"].value()) == pytest.approx((1e-4 + 9e-4) / 2)
    assert float(weighted["depth"].value()) == pytest.approx((near * 1e-4 + far * 9e-4) / 2)
    for name in ("depth", "sdf", "free_space"):
        assert torch.equal(weighted[name].row_weight, depth_noise_weights(depth_obs))
    assert weighted["colour"].row_weight is None
    assert torch.isclose(weighted["colour"].value(), plain["colour"].value())


def test_objective_equals_the_paper_losses_written_out(fitted_small_map):
    """The objective over real rendered rays against the paper's losses written as plain masked means
    (colour and depth over observed rays; SDF and free space per ray over its samples, then over rays;
    smoothness over valid points)."""
    import numpy as np

    from neb_slam_core.render.rays import sample_pixels
    from neb_slam_core.render.renderer import objective

    fm = fitted_small_map
    frame = fm.held_out[0]
    px = sample_pixels(frame, 256, np.random.default_rng(0), valid_depth_only=True)
    rays = px.to_world(torch.as_tensor(frame.T_world_cam, dtype=torch.float32))
    with torch.no_grad():
        obj, out = objective(fm.block_map, rays, fm.render, None, generator=torch.Generator().manual_seed(1))
    tr, w = fm.render.truncation_m, fm.render.weights
    obs = out.observed
    colour = ((out.rgb - rays.rgb) ** 2).mean(dim=1)[obs].mean()
    has_d = obs & (rays.depth_m > 0)
    depth = ((out.depth_m - rays.depth_m) ** 2)[has_d].mean()
    gap = rays.depth_m[:, None] - out.z
    per_ray = {"sdf": [], "free_space": []}
    for i in range(len(rays.depth_m)):
        if rays.depth_m[i] <= 0:
            continue
        v = out.sample_valid[i]
        band = v & (gap[i].abs() <= tr)
        front = v & (gap[i] > tr)
        if band.any():
            per_ray["sdf"].append(((out.sdf[i] * tr - gap[i])[band] ** 2).mean())
        if front.any():
            per_ray["free_space"].append(((out.sdf[i] - 1) ** 2)[front].mean())
    sdf, free = torch.stack(per_ray["sdf"]).mean(), torch.stack(per_ray["free_space"]).mean()
    values = obj.as_floats()
    for name, ref in (("colour", colour), ("depth", depth), ("sdf", sdf), ("free_space", free)):
        assert values[name] == pytest.approx(float(ref), rel=1e-5), name
    total = (
        w.colour * colour + w.depth * depth + w.sdf * sdf + w.free_space * free + w.smoothness * values["smoothness"]
    )
    assert values["total"] == pytest.approx(float(total), rel=1e-5)
