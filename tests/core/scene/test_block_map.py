import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from neb_slam_core.config import BlockConfig, HashGridConfig
from neb_slam_core.mapping.optimizer import MapOptimizer
from neb_slam_core.scene.block_map import BlockMap, covering_centre
from neb_slam_core.types import Intrinsics

SMALL_GRID = HashGridConfig(
    n_levels=4, n_features_per_level=2, log2_hashmap_size=12, base_resolution=4, max_resolution=32, init_scale=0.1
)


def make_map(**kw) -> BlockMap:
    return BlockMap(BlockConfig(edge_m=5.0, grid=SMALL_GRID, **kw), grid_backend="reference", seed=3)


def test_contains_and_local_coordinates():
    m = make_map()
    b = m.add_block([1.0, 2.0, 3.0])
    pts = torch.tensor([[1.0, 2.0, 3.0], [3.5, 4.5, 5.5], [3.51, 2.0, 3.0], [-1.5, -0.5, 0.5]])
    assert m.contains(pts).squeeze(1).tolist() == [True, True, False, True]
    assert torch.allclose(b.to_local(pts[:2]), torch.tensor([[0.5, 0.5, 0.5], [1.0, 1.0, 1.0]]))


def test_features_are_the_mean_over_overlapping_blocks_and_points_in_none_are_invalid():
    m = make_map()
    a = m.add_block([0.0, 0.0, 0.0])
    b = m.add_block([3.0, 0.0, 0.0])  # overlap for x in [0.5, 2.5]
    pts = torch.tensor([[-2.0, 0.0, 0.0], [1.5, 0.3, -0.2], [5.0, 1.0, 1.0], [9.0, 0.0, 0.0]])
    feats, valid = m.grid_features(pts)
    assert valid.tolist() == [True, True, True, False]
    fa = a.grid(a.to_local(pts))
    fb = b.grid(b.to_local(pts))
    assert torch.allclose(feats[0], fa[0])
    assert torch.allclose(feats[1], 0.5 * (fa[1] + fb[1]))
    assert torch.allclose(feats[2], fb[2])
    assert torch.equal(feats[3], torch.zeros_like(feats[3]))
    # restricting to block a only
    feats_a, valid_a = m.grid_features(pts, [a.block_id])
    assert valid_a.tolist() == [True, True, False, False]
    assert torch.allclose(feats_a[1], fa[1])
    q = m.query(pts)
    assert q.sdf.shape == (4,) and q.rgb.shape == (4, 3)
    assert q.sdf[3] == 0 and (q.rgb[3] == 0).all()


def test_frustum_selection():
    m = make_map()
    k = Intrinsics(100.0, 100.0, 50.0, 50.0, 100, 100)  # 53 degree field of view
    ahead = m.add_block([0.0, 0.0, 4.0]).block_id
    far_ahead = m.add_block([0.0, 0.0, 12.0]).block_id  # spans z 9.5..14.5
    behind = m.add_block([0.0, 0.0, -6.0]).block_id
    aside = m.add_block([20.0, 0.0, 4.0]).block_id
    grazing = m.add_block([4.4, 0.0, 6.0]).block_id  # x from 1.9: the frustum reaches x = 3 at z = 6
    T = np.eye(4)
    ids = m.blocks_in_frustum(T, k, near_m=0.1, far_m=6.0)
    assert ahead in ids and grazing in ids
    assert far_ahead not in ids and behind not in ids and aside not in ids
    assert far_ahead in m.blocks_in_frustum(T, k, near_m=0.1, far_m=10.0)
    # turn the camera around (180 degrees about y): now the block behind is in view
    T_back = np.diag([-1.0, 1.0, -1.0, 1.0])
    ids_back = m.blocks_in_frustum(T_back, k, 0.1, 8.0)
    assert behind in ids_back and ahead not in ids_back


def test_allocation_rule():
    m = make_map(alloc_threshold=0.2)
    pts = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [2.0, 3.0, 2.0]])
    first = m.allocate_if_needed(pts, [])
    assert first.tau == 1.0 and first.block is not None
    assert torch.allclose(first.block.centre, torch.tensor([1.0, 1.0, 2.0]))
    # all inside: no new block
    again = m.allocate_if_needed(pts, [0])
    assert again.tau == 0.0 and again.block is None and len(m) == 1
    # 1 of 5 outside: tau = 0.2 is not above the threshold
    pts5 = torch.cat([pts, torch.tensor([[1.0, 1.0, 1.0], [10.0, 0.0, 2.0]])])
    assert m.allocate_if_needed(pts5, [0]).block is None
    # 2 of 5 outside: tau = 0.4 > 0.2, centred at the mean of the two outside points
    pts5[3] = torch.tensor([10.0, 2.0, 4.0])
    alloc = m.allocate_if_needed(pts5, [0])
    assert abs(alloc.tau - 0.4) < 1e-9 and alloc.block is not None
    assert torch.allclose(alloc.block.centre, torch.tensor([10.0, 1.0, 3.0]))


def _two_sides(n_left: int = 60, n_right: int = 40) -> torch.Tensor:
    """Points at x = -4 (``n_left``) and x = +4 (``n_right``), spread 0.2 m in y and z."""
    g = torch.Generator().manual_seed(0)
    left = torch.tensor([-4.0, 0.0, 0.0]) + 0.2 * torch.rand(n_left, 3, generator=g)
    right = torch.tensor([4.0, 0.0, 0.0]) + 0.2 * torch.rand(n_right, 3, generator=g)
    return torch.cat([left, right])


def test_mean_allocation_stacks_blocks_between_two_sides_and_cover_does_not():
    # every point outside the mapped space, on two sides 8 m apart: the mean (x = -0.8) lies between
    # them and a 5 m cube there reaches neither (it ends 1.7 m short of the left side)
    pts = _two_sides()
    mean_map = make_map(alloc_centre="mean")
    for _ in range(3):  # the same view, frame after frame
        mean_map.allocate_if_needed(pts, list(range(len(mean_map))))
    assert len(mean_map) == 3
    centres = mean_map.centres()
    assert torch.allclose(centres, centres[0].expand_as(centres))  # three blocks in one place
    assert mean_map.allocation_tau(pts, [0, 1, 2])[0] == 1.0  # covering nothing

    cover_map = make_map(alloc_centre="cover")
    first = cover_map.allocate_if_needed(pts, [])
    # the mean shift climbs to the larger side: its block covers it, tau falls to 40 / 100
    assert first.tau == 1.0 and torch.allclose(first.block.centre, pts[:60].mean(0))
    second = cover_map.allocate_if_needed(pts, [0])
    assert abs(second.tau - 0.4) < 1e-9 and torch.allclose(second.block.centre, pts[60:].mean(0))
    assert cover_map.allocate_if_needed(pts, [0, 1]).block is None
    assert len(cover_map) == 2 and cover_map.allocation_tau(pts, [0, 1])[0] == 0.0


def test_covering_centre_keeps_the_mean_where_no_cube_holds_more():
    # 95 points at x = -4 and 5 at x = +4: the mean (x = -3.5) holds the 95, as does any shift
    pts = _two_sides(n_left=95, n_right=5)
    start = pts.mean(0)
    assert torch.equal(covering_centre(pts, start, 2.5), start)
    # one region of new space: the mean's cube holds every point
    one = pts[:95]
    assert torch.equal(covering_centre(one, one.mean(0), 2.5), one.mean(0))
    # 70 / 30: the mean (x = -1.6) holds the 70 left, the mean shift climbs to their own mean, which holds
    # the same 70: the paper's centre stays
    pts = _two_sides(n_left=70, n_right=30)
    assert torch.equal(covering_centre(pts, pts.mean(0), 2.5), pts.mean(0))


def test_covering_centre_moves_next_to_an_overlap_onto_the_larger_side():
    # 60 points spread over x in [2.6, 4.6] and 40 over x in [-4.6, -2.6]: the mean (x = 0.8) holds only
    # the points below x = 3.3; the mean shift climbs onto the 60, whose cube holds them all
    g = torch.Generator().manual_seed(1)
    right = torch.tensor([2.6, 0.0, 0.0]) + torch.rand(60, 3, generator=g) * torch.tensor([2.0, 0.2, 0.2])
    left = torch.tensor([-4.6, 0.0, 0.0]) + torch.rand(40, 3, generator=g) * torch.tensor([2.0, 0.2, 0.2])
    pts = torch.cat([right, left])
    start = pts.mean(0)
    held = int(((pts - start).abs().amax(-1) <= 2.5).sum())
    assert 0 < held < 60
    moved = covering_centre(pts, start, 2.5)
    assert int(((pts - moved).abs().amax(-1) <= 2.5).sum()) == 60
    assert torch.allclose(moved, right.mean(0))


def test_adding_a_block_keeps_optimizer_state_of_existing_blocks():
    m = make_map()
    m.add_block([0.0, 0.0, 0.0])
    opt = MapOptimizer(m, grid_lr=1e-2, decoder_lr=1e-2)
    pts = torch.rand(256, 3) * 4 - 2
    for _ in range(3):
        opt.zero_grad()
        m.query(pts).sdf.square().mean().backward()
        opt.step()
    table0 = m.blocks[0].grid.table
    state_before = {k: v.clone() for k, v in opt.optimizer.state[table0].items()}
    values_before = table0.detach().clone()
    m.add_block([4.0, 0.0, 0.0])
    assert opt.sync() == 1
    assert len(opt.optimizer.param_groups) == 3  # decoders + two blocks
    for k, v in opt.optimizer.state[table0].items():
        assert torch.equal(v, state_before[k])
    assert torch.equal(table0.detach(), values_before)
    opt.zero_grad()
    m.query(torch.rand(256, 3) * 8 - 2).sdf.square().mean().backward()
    opt.step()
    assert opt.optimizer.state[m.blocks[1].grid.table]["step"] == 1
    assert opt.optimizer.state[table0]["step"] == 4


def test_map_optimizer_steps_like_torchs_default_adam():
    """The fused Adam kernel the map optimiser uses gives the default implementation's update (same
    gradients, five steps, a block added after two)."""
    import copy

    m = make_map()
    m.add_block([0.0, 0.0, 0.0])
    twin = copy.deepcopy(m)
    start = m.blocks[0].grid.table.detach().clone()
    opt = MapOptimizer(m, grid_lr=1e-2, decoder_lr=2e-2)
    ref = torch.optim.Adam(
        [{"params": list(twin.decoders.parameters()), "lr": 2e-2}, {"params": [twin.blocks[0].grid.table], "lr": 1e-2}],
        betas=(0.9, 0.99),
        eps=1e-15,
    )
    g = torch.Generator().manual_seed(0)
    for step in range(5):
        if step == 2:
            m.add_block([4.0, 0.0, 0.0])
            twin.add_block([4.0, 0.0, 0.0])
            ref.add_param_group({"params": [twin.blocks[1].grid.table], "lr": 1e-2})
        pts = torch.rand(256, 3, generator=g) * 8 - 2
        for mp, o in ((m, opt), (twin, ref)):
            o.zero_grad()
            mp.query(pts).sdf.square().mean().backward()
            o.step()
    for (name, p), p_ref in zip(m.named_parameters(), twin.parameters()):
        torch.testing.assert_close(p, p_ref, rtol=1e-5, atol=1e-7, msg=name)
    assert (m.blocks[0].grid.table.detach() - start).abs().max() > 1e-3  # the steps moved the table


def test_param_mb_is_blocks_times_grid_plus_decoders():
    m = make_map()
    m.add_block([0.0, 0.0, 0.0])
    m.add_block([4.0, 0.0, 0.0])
    per_block = m.blocks[0].grid.param_bytes
    decoders = sum(p.numel() * 4 for p in m.decoders.parameters())
    # geometry (48+8)->32->16 and colour (48+15)->32->3 for this small grid (L*F = 8)
    assert decoders == 4 * ((56 * 32 + 32) + (32 * 16 + 16) + (63 * 32 + 32) + (32 * 3 + 3))
    assert abs(m.param_mb() - (2 * per_block + decoders) / 1e6) < 1e-12


def test_features_blend_continuously_across_a_face_inside_another_block():
    m = make_map()  # blend_m = 0.5 by default
    a = m.add_block([0.0, 0.0, 0.0])  # x in [-2.5, 2.5]
    b = m.add_block([3.0, 0.0, 0.0])  # x in [0.5, 5.5]
    # 0.1 m inside a's face: a weighs 0.1 / 0.5 = 0.2, b (1.9 m from its faces) weighs 1
    p = torch.tensor([[2.4, 0.3, -0.2]])
    feats, _ = m.grid_features(p)
    fa, fb = a.grid(a.to_local(p)), b.grid(b.to_local(p))
    assert torch.allclose(feats, (0.2 * fa + fb) / 1.2, atol=1e-6)
    # just inside and just outside a's face: the same features (continuous), although a's grid differs
    inner, outer = torch.tensor([[2.5 - 1e-5, 0.3, -0.2]]), torch.tensor([[2.5 + 1e-5, 0.3, -0.2]])
    assert torch.allclose(m.grid_features(inner)[0], m.grid_features(outer)[0], atol=1e-4)
    assert not torch.allclose(a.grid(a.to_local(inner)), b.grid(b.to_local(inner)), atol=1e-4)
    # with blend_m = 0 the paper's plain mean holds up to the face
    plain = BlockMap(BlockConfig(edge_m=5.0, grid=SMALL_GRID, blend_m=0.0), grid_backend="reference", seed=3)
    pa, pb = plain.add_block([0.0, 0.0, 0.0]), plain.add_block([3.0, 0.0, 0.0])
    assert torch.allclose(
        plain.grid_features(p)[0], 0.5 * (pa.grid(pa.to_local(p)) + pb.grid(pb.to_local(p))), atol=1e-6
    )


def _fast_map(blend_m: float, dtype=torch.float32) -> BlockMap:
    """Three overlapping blocks on the C++ path, with table values large enough to show errors."""
    from neb_slam_core.scene import hash_grid as hg

    reason = hg.fast_path_unavailable_reason()
    if reason is not None:  # the fast path is part of the product: a failed build fails, never skips
        raise AssertionError(f"the hash-grid C++ extension did not build: {reason}")
    m = BlockMap(BlockConfig(edge_m=5.0, grid=SMALL_GRID, blend_m=blend_m), grid_backend="fast", seed=3)
    for centre in ([0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [1.5, 2.0, -1.0]):
        m.add_block(centre)
    m = m.to(dtype)
    gen = torch.Generator().manual_seed(4)
    with torch.no_grad():
        for b in m.blocks:
            b.grid.table.copy_(torch.rand(b.grid.table.shape, generator=gen, dtype=dtype) * 2 - 1)
    return m


def _points(n: int, dtype=torch.float32) -> torch.Tensor:
    """Points over the three blocks and around them: one block, two, three, none, and exactly on faces."""
    gen = torch.Generator().manual_seed(7)
    p = torch.rand(n, 3, generator=gen, dtype=torch.float64) * torch.tensor([10.0, 9.0, 8.0]) - torch.tensor(
        [3.5, 3.5, 4.5]
    )
    faces = torch.tensor(
        [[2.5, 0.3, 0.1], [0.5, -1.0, 0.2], [3.0, 4.5, -1.0], [-2.5, -2.5, -2.5], [5.5, 0.0, 0.0]], dtype=torch.float64
    )
    return torch.cat([p, faces]).to(dtype)


def test_blended_features_by_the_kernel_equal_the_torch_sum():
    # The kernel (no gradient wanted) against the torch path of the same map (taken when a gradient is
    # wanted), which the tests above check by hand: the same features wherever the blocks overlap.
    for blend_m, dtype, tol in ((0.5, torch.float32, 1e-6), (0.0, torch.float32, 1e-6), (0.5, torch.float64, 1e-12)):
        m = _fast_map(blend_m, dtype)
        p = _points(4000, dtype)
        ids = [0, 1, 2]
        with torch.no_grad():
            feats, valid = m.grid_features(p, ids)
        q = p.clone().requires_grad_(True)
        ref, ref_valid = m.grid_features(q, ids)  # grad mode on, points need a gradient: the torch path
        assert ref.requires_grad and not feats.requires_grad  # the two calls took different paths
        inside = m.contains(p, ids)
        counts = inside.sum(dim=1)
        assert {0, 1, 2, 3} <= set(counts.tolist())  # the points cover no block, one, two and all three
        assert torch.equal(valid, ref_valid) and torch.equal(valid, counts > 0)
        torch.testing.assert_close(feats, ref.detach(), rtol=0, atol=tol)
        assert torch.equal(feats[~valid], torch.zeros_like(feats[~valid]))
        # a subset of the blocks, in another order: the same as the torch path on that subset
        with torch.no_grad():
            sub, _ = m.grid_features(p, [2, 0])
        torch.testing.assert_close(sub, m.grid_features(q, [2, 0])[0].detach(), rtol=0, atol=tol)


def test_the_kernel_is_not_used_when_a_gradient_is_wanted():
    from neb_slam_core.scene.freeze import frozen
    from neb_slam_core.scene.hash_grid import encode_blended

    m = _fast_map(0.5)
    p = _points(100)
    grids = [b.grid for b in m.blocks]

    def kernel_runs(points):
        return encode_blended(points, m.centres(), grids, 5.0, 0.5) is not None

    assert not kernel_runs(p)  # grad mode on and the tables train (mapping)
    with torch.no_grad():
        assert kernel_runs(p)  # rendering for evaluation, meshing
    with frozen(m):
        assert kernel_runs(p)  # tracking: the map is frozen and the points need no gradient
        assert not kernel_runs(p.clone().requires_grad_(True))  # autograd spatial gradients
    with torch.no_grad():
        assert encode_blended(p, m.centres(), [make_map().add_block([0.0, 0.0, 0.0]).grid], 5.0, 0.5) is None
    # mapping: gradients reach every block through the torch path
    feats, _ = m.grid_features(p)
    feats.sum().backward()
    assert all(b.grid.table.grad is not None and b.grid.table.grad.abs().sum() > 0 for b in m.blocks)


def test_prepare_loads_the_cpp_kernels_unless_the_reference_is_asked_for(monkeypatch):
    """``neb-slam run`` builds the C++ extension before its first frame (``_ext.prepare``), so a first-use
    compile is not timed as that frame; the reference backend never asks for it, and a failed build
    leaves "auto" to fall back."""
    from neb_slam_core.scene import _ext, hash_grid

    builds = []

    def broken_build():
        builds.append(1)
        raise RuntimeError("no C++ compiler (simulated)")

    monkeypatch.setattr(_ext, "_module", None)
    monkeypatch.setattr(_ext, "_failure", None)
    monkeypatch.setattr(_ext, "_build", broken_build)
    monkeypatch.setattr(hash_grid, "_fallback_warned", False)
    _ext.prepare("reference")
    assert builds == []
    _ext.prepare("auto")
    assert builds == [1]
    _ext.prepare("fast")  # the failure is remembered: no second build, and no error here ...
    assert builds == [1]
    m = BlockMap(BlockConfig(grid=SMALL_GRID), grid_backend="auto")
    m.add_block([0.0, 0.0, 0.0])
    with pytest.warns(RuntimeWarning, match="simulated"):  # ... but where the map uses it: one fallback warning
        q = m.query(torch.zeros(4, 3))
    assert q.valid.all()


def test_spatial_gradients_in_closed_form_equal_autograd_through_the_torch_path():
    # BlockMap.spatial_gradients (the C++ features with their derivatives, the one-blob slopes, the
    # decoders' forward mode) against autograd's gradients of query() on the torch path, over points in
    # one, two and three blending blocks, on faces and in none; float64 leaves only rounding between them.
    from neb_slam_core.tracking.gauss_newton import spatial_gradients_autograd

    for blend_m in (0.5, 0.0):
        m = _fast_map(blend_m, torch.float64)
        with torch.no_grad():  # decoder weights large enough that ReLUs switch and colours spread
            for p in m.decoders.parameters():
                p.normal_(0.0, 0.25, generator=torch.Generator().manual_seed(11))
        p = _points(3000, torch.float64)
        for ids in ([0, 1, 2], [1], [2, 0]):
            closed = m.spatial_gradients(p, ids)
            auto = spatial_gradients_autograd(m, p, ids)
            assert closed.shape == (4, p.shape[0], 3)
            scale = float(auto.abs().max())
            assert scale > 1.0  # gradients that show errors
            torch.testing.assert_close(closed, auto, rtol=0, atol=1e-9 * scale)
            outside = ~m.contains(p, ids).any(dim=1)
            assert bool(outside.any()) and torch.equal(closed[:, outside], torch.zeros_like(closed[:, outside]))


def test_spatial_gradients_need_the_cpp_path():
    m = BlockMap(BlockConfig(edge_m=5.0, grid=SMALL_GRID), grid_backend="reference", seed=3)
    m.add_block([0.0, 0.0, 0.0])
    assert m.spatial_gradients(torch.zeros(4, 3), [0]) is None  # the caller differentiates otherwise
    assert _fast_map(0.5).spatial_gradients(torch.zeros(4, 3), []) is None


# A block of edge 4 m at the origin with 1 m voxels (centres at +/-0.5 and +/-1.5 m), seen by a 4x4 camera
# at the origin looking along +z: pixel u = round(2 x / z + 1.6), likewise v. In front of the camera the
# voxel centres lie at z = 0.5 (only x = y = -0.5 lands in the image, on pixel 0) and at z = 1.5 (x and y
# in {-1.5, -0.5, 0.5} land on pixels 0, 1, 2; 1.5 on pixel 4, outside).
OBS_K = Intrinsics(2.0, 2.0, 1.6, 1.6, 4, 4)
OBS_TR = 0.1


#: mark_observed's two paths: torch (a map on the reference backend) and the C++ kernel (the fast one)
OBSERVED_PATHS = ("reference", "fast")


@pytest.fixture(params=OBSERVED_PATHS)
def backend(request) -> str:
    """Each of mark_observed's paths; the fast one fails (never skips) without the kernels."""
    if request.param == "fast":
        request.getfixturevalue("fast_ext")
    return request.param


def observed_map(backend: str = "reference") -> BlockMap:
    m = BlockMap(BlockConfig(edge_m=4.0, grid=SMALL_GRID, observed_voxel_m=1.0), grid_backend=backend, seed=3)
    m.add_block([0.0, 0.0, 0.0])
    return m


def observed_centres(m: BlockMap) -> set[tuple[float, float, float]]:
    idx = m.blocks[0].observed.nonzero()
    return {tuple(float(v) for v in (-2.0 + (i + 0.5) * 1.0).tolist()) for i in idx}


def test_a_keyframe_observes_the_voxels_in_its_view_up_to_its_surface(backend):
    m = observed_map(backend)
    assert m.blocks[0].observed.shape == (4, 4, 4) and not m.blocks[0].observed.any()
    # surface 1.2 m away: a centre counts up to 1.2 + tr + half the voxel diagonal (0.87) = 2.17 m deep; a
    # voxel's footprint there (2 px x 1 m / 1.2 m = 1.7 px) is under two pixels: each centre is compared
    # with its own pixel's depth
    assert m.mark_observed(np.full((4, 4), 1.2, np.float32), OBS_K, np.eye(4), OBS_TR) == {0}
    near = {(-0.5, -0.5, 0.5)}
    far = {(x, y, 1.5) for x in (-1.5, -0.5, 0.5) for y in (-1.5, -0.5, 0.5)}
    assert observed_centres(m) == near | far
    assert m.mark_observed(np.full((4, 4), 1.2, np.float32), OBS_K, np.eye(4), OBS_TR) == set()  # nothing new


def test_space_behind_the_surface_and_pixels_without_depth_stay_unobserved(backend):
    m = observed_map(backend)
    depth = np.full((4, 4), 0.2, np.float32)  # the z = 1.5 centres lie behind 0.2 + 0.1 + 0.87
    assert m.mark_observed(depth, OBS_K, np.eye(4), OBS_TR) == {0}
    assert observed_centres(m) == {(-0.5, -0.5, 0.5)}
    m = observed_map(backend)
    depth = np.full((4, 4), 1.2, np.float32)
    depth[2, 2] = 0.0  # the pixel of x = y = 0.5 at z = 1.5
    m.mark_observed(depth, OBS_K, np.eye(4), OBS_TR)
    assert len(observed_centres(m)) == 9 and (0.5, 0.5, 1.5) not in observed_centres(m)


def test_a_moved_camera_observes_the_moved_voxels(backend):
    m = observed_map(backend)
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]  # one voxel to the right: every observed centre moves by +1 m in x
    m.mark_observed(np.full((4, 4), 1.2, np.float32), OBS_K, T, OBS_TR)
    inside = {(x, y, 1.5) for x in (-0.5, 0.5, 1.5) for y in (-1.5, -0.5, 0.5)} | {(0.5, -0.5, 0.5)}
    assert observed_centres(m) == inside


def test_observed_answers_by_voxel_and_everything_counts_without_a_record():
    m = observed_map()
    m.mark_observed(np.full((4, 4), 1.2, np.float32), OBS_K, np.eye(4), OBS_TR)
    pts = torch.tensor([[-0.9, -0.1, 0.2], [0.5, 0.5, 0.5], [0.2, 0.3, 1.9], [0.2, 0.3, 2.5], [1.2, 0.3, 1.5]])
    # in the (-0.5, -0.5, 0.5) voxel; an unseen voxel; in (0.5, 0.5, 1.5); outside the block; (1.5, 0.5, 1.5)
    assert m.observed(pts).tolist() == [True, False, True, False, False]
    without = make_map(observed_voxel_m=0.0)
    without.add_block([0.0, 0.0, 0.0])
    assert without.blocks[0].voxel_m == 0.0
    assert without.observed(pts).all()


@pytest.mark.parametrize("seed", range(4))
def test_the_observed_kernel_marks_the_voxels_of_the_torch_path(fast_ext, seed):
    # a 5 m block of 5 cm voxels seen by a 120 x 160 camera at a random pose over a bumpy, holed surface,
    # twice (the second view adds to the first): the two paths mark the same voxels, one for one
    rng = np.random.default_rng(seed)
    k = Intrinsics(fx=150.0, fy=150.0, cx=79.5, cy=59.5, width=160, height=120)
    depth = (1.0 + 2.0 * rng.random() + 0.3 * rng.random((120, 160))).astype(np.float32)
    depth[rng.random((120, 160)) < 0.1] = 0.0
    maps = {}
    for backend in OBSERVED_PATHS:
        m = BlockMap(BlockConfig(edge_m=5.0, grid=SMALL_GRID, observed_voxel_m=0.05), grid_backend=backend, seed=3)
        m.add_block([0.3, -0.2, 1.5])
        m.add_block([2.0, 1.0, 4.0])
        maps[backend] = m
    for _ in range(2):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(0.3 * rng.standard_normal(3)).as_matrix()
        T[:3, 3] = 0.5 * rng.standard_normal(3)
        grown = {b: m.mark_observed(depth, k, T, 0.1) for b, m in maps.items()}
        assert grown["fast"] == grown["reference"]
        for ref, fast in zip(maps["reference"].blocks, maps["fast"].blocks):
            assert torch.equal(ref.observed, fast.observed)
    assert sum(int(b.observed.sum()) for b in maps["fast"].blocks) > 10_000  # the views saw something
