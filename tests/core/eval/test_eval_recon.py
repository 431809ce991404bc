"""Reconstruction metrics: accuracy / completion / ratio, culling, ray-cast depth and Depth L1."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.special import erfcx

from neb_slam_core.errors import DatasetError
from neb_slam_core.eval.raycast import RayCaster
from neb_slam_core.eval.recon import (
    CullConfig,
    DepthL1Config,
    ReconConfig,
    evaluate_depth_l1,
    evaluate_reconstruction,
    load_mesh,
    sample_surface_points,
    sample_virtual_views,
    visible_mask,
)
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.types import Intrinsics

NO_DEPTH = DepthL1Config(n_views=0)
SMALL_CAM = Intrinsics(32.0, 32.0, 31.5, 23.5, 64, 48)  # x/z in [-1, 1], y/z in [-0.75, 0.75]
# camera at +z looking down -z (180 degrees about y keeps the frame right-handed)
FLIP_Y = np.diag([-1.0, 1.0, -1.0])


def patch(x0, x1, y0, y1, z, subdivisions: int = 0) -> trimesh.Trimesh:
    """An axis-aligned rectangle in the plane z = const (two triangles, optionally subdivided)."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    mesh = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return mesh


def room() -> trimesh.Trimesh:
    """A closed 4 x 3 x 2.5 m box: from inside every ray hits a wall."""
    return trimesh.creation.box(extents=(4.0, 3.0, 2.5))


# ---------------------------------------------------------------------------------------------- 3D metrics


def test_mesh_against_itself_scores_perfectly():
    mesh = room()
    cfg = ReconConfig(n_points=20_000, depth_l1=DepthL1Config(n_views=6, intrinsics=SMALL_CAM))
    res = evaluate_reconstruction(mesh, mesh, cfg, progress=False)
    assert res.accuracy_cm == 0.0 and res.completion_cm == 0.0
    assert res.completion_ratio_pct == 100.0
    assert res.depth_l1_cm == 0.0 and res.n_depth_views == 6 and res.depth_rec_coverage_pct == 100.0
    assert (res.n_rec_points, res.n_gt_points, res.culled) == (20_000, 20_000, False)


def test_plane_shifted_along_its_normal_by_one_cm():
    # Same triangulation and seed: every reconstruction point is a ground-truth point moved by exactly
    # 1 cm along the normal, and the in-plane neighbours are farther, so both means are 1 cm.
    gt = patch(0, 1, 0, 1, 0.0)
    rec = patch(0, 1, 0, 1, 0.01)
    res = evaluate_reconstruction(rec, gt, ReconConfig(n_points=20_000, depth_l1=NO_DEPTH), progress=False)
    assert res.accuracy_cm == pytest.approx(1.0, abs=1e-9)
    assert res.completion_cm == pytest.approx(1.0, abs=1e-9)
    assert res.completion_ratio_pct == 100.0
    tight = ReconConfig(n_points=20_000, completion_threshold_m=0.009, depth_l1=NO_DEPTH)
    assert evaluate_reconstruction(rec, gt, tight, progress=False).completion_ratio_pct == 0.0


def test_plane_shift_with_independent_samples_matches_the_poisson_expectation():
    # Different triangulation: the reconstruction's samples fall independently of the ground truth's.
    # For n uniform points on area A (density lam = n / A) the in-plane nearest-neighbour distance r has
    # P(r > x) = exp(-pi lam x^2), so E[sqrt(d^2 + r^2)] = d + exp(pi lam d^2) int_d^inf exp(-pi lam s^2) ds
    #   = d + erfcx(d sqrt(pi lam)) / (2 sqrt(lam)).
    # n = 50,000 on 1 m^2, d = 1 cm: 1.0309 cm; the sampling noise of the mean is ~1e-4 cm, the border
    # (points near the edge have fewer neighbours) adds ~2e-4 cm.
    n, d = 50_000, 0.01
    gt = patch(0, 1, 0, 1, 0.0)
    rec = patch(0, 1, 0, 1, d, subdivisions=2)
    res = evaluate_reconstruction(rec, gt, ReconConfig(n_points=n, depth_l1=NO_DEPTH), progress=False)
    expected_cm = 100 * (d + erfcx(d * np.sqrt(np.pi * n)) / (2 * np.sqrt(n)))
    assert expected_cm == pytest.approx(1.0309, abs=1e-4)
    assert res.accuracy_cm == pytest.approx(expected_cm, abs=2e-3)
    assert res.completion_cm == pytest.approx(expected_cm, abs=2e-3)
    # the sampling floor is the same expectation at d = 0: 1 / (2 sqrt(lam)) = 0.2236 cm, whatever the
    # reconstruction; with 4x the points it halves
    assert res.sampling_floor_cm == pytest.approx(100 / (2 * np.sqrt(n)), abs=3e-3)
    dense = evaluate_reconstruction(rec, gt, ReconConfig(n_points=4 * n, depth_l1=NO_DEPTH), progress=False)
    assert dense.sampling_floor_cm == pytest.approx(100 / (4 * np.sqrt(n)), abs=2e-3)
    assert dense.n_points == 4 * n


# ---------------------------------------------------------------------------------------------- culling


def culling_scene() -> dict[str, trimesh.Trimesh]:
    """Patches around a camera at the origin looking along +z (SMALL_CAM)."""
    return {
        "seen": patch(-0.5, 0.5, -0.5, 0.5, 2.0),  # in the frustum, in front
        "hidden": patch(-0.25, 0.25, -0.25, 0.25, 4.0),  # in the frustum but entirely behind "seen"
        "behind_camera": patch(-0.5, 0.5, -0.5, 0.5, -2.0),
        "off_to_the_side": patch(5.0, 6.0, -0.5, 0.5, 2.0),  # x/z >= 2.5: outside the image
        "too_far": patch(4.0, 5.0, -0.5, 0.5, 12.0),  # in the image, beyond the 10 m max depth
    }


def test_culling_keeps_only_what_the_camera_saw():
    parts = culling_scene()
    gt = trimesh.util.concatenate(list(parts.values()))
    caster = RayCaster(gt)
    for name, mesh in parts.items():
        pts = sample_surface_points(mesh, 500, 0)
        mask = visible_mask(pts, np.eye(4)[None], SMALL_CAM, caster)
        assert mask.all() if name == "seen" else not mask.any(), name
    far = sample_surface_points(parts["too_far"], 200, 0)
    assert visible_mask(far, np.eye(4)[None], SMALL_CAM, caster, CullConfig(max_depth_m=15.0)).all()
    # without an occluder the hidden patch counts as seen
    hidden = sample_surface_points(parts["hidden"], 200, 0)
    assert visible_mask(hidden, np.eye(4)[None], SMALL_CAM, None).all()


def test_culling_takes_the_union_over_cameras():
    parts = culling_scene()
    gt = trimesh.util.concatenate(list(parts.values()))
    # a second camera at z = 5 looking back at the hidden patch (which now hides the first one)
    cams = np.stack([np.eye(4), make_pose(FLIP_Y, [0.0, 0.0, 5.0])])
    hidden = sample_surface_points(parts["hidden"], 300, 1)
    seen = sample_surface_points(parts["seen"], 300, 1)
    caster = RayCaster(gt)
    assert not visible_mask(hidden, cams[:1], SMALL_CAM, caster).any()
    assert visible_mask(hidden, cams[1:], SMALL_CAM, caster).all()
    assert not visible_mask(seen, cams[1:], SMALL_CAM, caster).any()
    assert visible_mask(np.r_[hidden, seen], cams, SMALL_CAM, caster).all()


def test_occlusion_tolerance_keeps_points_just_behind_the_surface():
    caster = RayCaster(patch(-1, 1, -1, 1, 2.0))
    pts = np.array([[0.1, 0.1, 1.95], [0.1, 0.1, 2.02], [0.1, 0.1, 2.1]])  # in front, 2 cm and 10 cm behind
    np.testing.assert_array_equal(visible_mask(pts, np.eye(4)[None], SMALL_CAM, caster), [True, True, False])
    strict = CullConfig(occlusion_tolerance_m=0.01)
    np.testing.assert_array_equal(visible_mask(pts, np.eye(4)[None], SMALL_CAM, caster, strict), [True, False, False])


def test_culling_changes_completion_to_the_observed_part():
    parts = culling_scene()
    gt = trimesh.util.concatenate(list(parts.values()))
    rec = parts["seen"]  # the reconstruction covers exactly what the camera saw
    cfg = ReconConfig(n_points=20_000, depth_l1=NO_DEPTH)
    whole = evaluate_reconstruction(rec, gt, cfg, progress=False)
    culled = evaluate_reconstruction(rec, gt, cfg, T_world_cams=np.eye(4)[None], intrinsics=SMALL_CAM, progress=False)
    # unculled: only the ground-truth points on "seen" (1 m^2 of 4.25 m^2) are near the reconstruction
    assert whole.completion_ratio_pct == pytest.approx(100 / 4.25, abs=1.5)
    assert culled.culled and culled.completion_ratio_pct == 100.0
    assert whole.completion_cm > 100.0 and culled.completion_cm < 1.0
    # the culled ground-truth points are all >= 1.5 m from the reconstruction: accuracy is unchanged
    assert culled.accuracy_cm == whole.accuracy_cm
    assert culled.n_gt_points == pytest.approx(20_000 / 4.25, rel=0.05)
    assert culled.n_rec_points == 20_000


def test_culling_everything_away_is_a_clear_error():
    gt = patch(-0.5, 0.5, -0.5, 0.5, 2.0)
    looking_away = make_pose(FLIP_Y, np.zeros(3))
    with pytest.raises(DatasetError, match="same world frame"):
        evaluate_reconstruction(
            gt,
            gt,
            ReconConfig(n_points=100, depth_l1=NO_DEPTH),
            T_world_cams=looking_away[None],
            intrinsics=SMALL_CAM,
            progress=False,
        )


# ---------------------------------------------------------------------------------------------- depth


def test_render_depth_is_z_depth_along_the_optical_axis():
    caster = RayCaster(patch(-10, 10, -10, 10, 2.0))
    depth = caster.render_depth(np.eye(4), SMALL_CAM)
    assert depth.shape == (48, 64) and depth.dtype == np.float32
    np.testing.assert_allclose(depth, 2.0, atol=1e-6)  # fronto-parallel: same z everywhere, not ray length
    # a camera at x = -1 looking along +x (optical z = world x) at the plane x = 2: depth 3
    wall = trimesh.Trimesh(patch(-10, 10, -10, 10, 0.0).vertices[:, [2, 0, 1]] + [2.0, 0, 0], [[0, 1, 2], [0, 2, 3]])
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: cam x, y, z in the world
    np.testing.assert_allclose(RayCaster(wall).render_depth(make_pose(R, [-1.0, 0, 0]), SMALL_CAM), 3.0, atol=1e-6)
    # looking away: nothing hit, depth 0
    assert not RayCaster(patch(-10, 10, -10, 10, 2.0)).render_depth(make_pose(FLIP_Y, np.zeros(3)), SMALL_CAM).any()


def test_depth_l1_of_a_plane_moved_one_cm_toward_the_camera():
    gt = patch(-10, 10, -10, 10, 2.0)
    rec = patch(-10, 10, -10, 10, 1.99)
    cfg = DepthL1Config(intrinsics=SMALL_CAM)
    l1, coverage, n = evaluate_depth_l1(rec, gt, cfg, T_world_cams=np.eye(4)[None])
    assert n == 1 and coverage == 100.0
    assert l1 == pytest.approx(0.01, abs=1e-6)  # depth images are float32
    # a hole-free but smaller reconstruction: L1 over the shared pixels, coverage says what is missing
    small = patch(-1, 1, -10, 10, 1.99)  # x/z within +-0.5: only the middle half of the columns
    l1, coverage, _ = evaluate_depth_l1(small, gt, cfg, T_world_cams=np.eye(4)[None])
    assert l1 == pytest.approx(0.01, abs=1e-6) and coverage == pytest.approx(50.0, abs=100 / 64)


def test_virtual_views_look_at_the_surface_and_are_seeded():
    mesh = room()
    caster = RayCaster(mesh)
    cfg = DepthL1Config(n_views=10, intrinsics=SMALL_CAM)
    T1, d1 = sample_virtual_views(mesh, caster, cfg, np.random.default_rng(3))
    T2, _ = sample_virtual_views(mesh, caster, cfg, np.random.default_rng(3))
    np.testing.assert_array_equal(T1, T2)
    assert T1.shape == (10, 4, 4) and d1.shape == (10, 48, 64)
    assert (d1 > 0).all()  # min_gt_coverage = 1: every pixel sees a wall
    lo, hi = mesh.bounds
    assert ((T1[:, :3, 3] >= lo) & (T1[:, :3, 3] <= hi)).all()
    for T in T1:
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    # the centre pixel looks at the drawn surface point, which lies on a wall of the box
    centre = caster.render_depth(T1, Intrinsics(1.0, 1.0, 0.0, 0.0, 1, 1))[:, 0, 0]
    hit = T1[:, :3, 3] + centre[:, None] * T1[:, :3, 2]
    on_wall = np.isclose(np.abs(hit), np.array([2.0, 1.5, 1.25]), atol=1e-5).any(axis=1)
    assert on_wall.all()


def test_views_that_miss_the_ground_truth_are_rejected():
    # a single plane seen from inside its (flat) bounding box: no view is fully covered
    mesh = patch(0, 1, 0, 1, 0.0)
    cfg = DepthL1Config(n_views=3, intrinsics=SMALL_CAM, max_draws_per_view=2)
    T, d = sample_virtual_views(mesh, RayCaster(mesh), cfg, np.random.default_rng(0))
    assert len(T) == 0 and d.shape == (0, 48, 64)


# ---------------------------------------------------------------------------------------------- files


def test_load_mesh_round_trip_and_errors(tmp_path):
    path = tmp_path / "room.ply"
    room().export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12
    with pytest.raises(DatasetError, match="not found"):
        load_mesh(tmp_path / "missing.ply")
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(cloud)
    with pytest.raises(DatasetError, match="no faces"):
        load_mesh(cloud)


def test_render_depth_in_chunks_matches_one_call(monkeypatch):
    import neb_slam_core.eval.raycast as raycast

    mesh = room()
    caster = RayCaster(mesh)
    T, _ = sample_virtual_views(mesh, caster, DepthL1Config(n_views=5, intrinsics=SMALL_CAM), np.random.default_rng(4))
    whole = caster.render_depth(T, SMALL_CAM)
    monkeypatch.setattr(raycast, "MAX_RAYS_PER_CALL", 2 * 64 * 48)  # two views per call: 3 calls
    np.testing.assert_array_equal(caster.render_depth(T, SMALL_CAM), whole)
    np.testing.assert_array_equal(caster.render_depth(T[3], SMALL_CAM), whole[3])
