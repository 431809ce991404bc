"""ATE / RPE: association, rigid alignment and the error statistics, on hand-worked trajectories."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neb_slam_core.errors import DatasetError
from neb_slam_core.eval.trajectory_metrics import (
    align_rigid,
    associate_trajectories,
    compute_rpe,
    evaluate_ate,
    evaluate_rpe,
    rpe_pairs,
)
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.io.trajectory import Trajectory, read_tum_trajectory

NS = 1_000_000_000


def random_pose(rng: np.random.Generator, scale: float = 2.0) -> np.ndarray:
    return make_pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * scale)


def poses_at(positions: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poses with random orientations at the given camera centres."""
    return np.stack([make_pose(Rotation.random(random_state=rng).as_matrix(), p) for p in positions])


def stamps(n: int, dt_s: float = 0.1, t0_s: float = 100.0) -> np.ndarray:
    return (np.round((t0_s + np.arange(n) * dt_s) * NS)).astype(np.int64)


def cube_corners() -> np.ndarray:
    """The 8 corners (+-1, +-1, +-1): centred, with covariance sum 8 I."""
    return np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])


def shifted(poses: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    out = poses.copy()
    out[:, :3, 3] += offsets
    return out


# ---------------------------------------------------------------------------------------------- alignment


def test_align_rigid_recovers_known_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    T = random_pose(rng)
    dst = src @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(align_rigid(src, dst), T, atol=1e-12)


def test_align_rigid_planar_points_never_returns_a_reflection():
    # Coplanar points: H has a zero singular value, so the unconstrained orthogonal fit is as good
    # with the mirror image; only the det fix makes the answer the proper rotation that was applied.
    rng = np.random.default_rng(2)
    src = np.c_[rng.normal(size=(10, 2)), np.zeros(10)]
    for _ in range(20):
        T = random_pose(rng)
        dst = src @ T[:3, :3].T + T[:3, 3]
        got = align_rigid(src, dst)
        assert np.linalg.det(got[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(got, T, atol=1e-10)


def test_align_rigid_mirrored_data_matches_scipy_wahba_solution():
    # The best fit to a mirror image is a reflection; the constrained optimum must be the proper
    # rotation that scipy's independent solver of the same least-squares problem finds.
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3)) * [3.0, 2.0, 1.0]
    dst = src * [1.0, 1.0, -1.0] + [0.5, -1.0, 2.0]
    got = align_rigid(src, dst)
    assert np.linalg.det(got[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    ref, _ = Rotation.align_vectors(dst - dst.mean(0), src - src.mean(0))
    np.testing.assert_allclose(got[:3, :3], ref.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(got[:3, 3], dst.mean(0) - got[:3, :3] @ src.mean(0), atol=1e-12)


def test_align_rigid_rejects_too_few_points():
    with pytest.raises(ValueError, match="at least 3"):
        align_rigid(np.zeros((2, 3)), np.zeros((2, 3)))


# ---------------------------------------------------------------------------------------------- ATE


def test_rigidly_moved_trajectory_has_zero_ate_after_alignment():
    rng = np.random.default_rng(4)
    t = np.linspace(0, 2 * np.pi, 60)
    gt = Trajectory(stamps(60), poses_at(np.c_[np.cos(t), np.sin(2 * t), 0.3 * t], rng))
    T_est_gt = random_pose(rng, scale=5.0)  # the estimate lives in another world frame
    est = Trajectory(gt.stamps_ns, T_est_gt @ gt.poses)
    ate = evaluate_ate(est, gt)
    assert ate.n_matched == 60
    assert ate.rmse_m < 1e-9 and ate.max_m < 1e-9
    np.testing.assert_allclose(ate.T_gt_est, np.linalg.inv(T_est_gt), atol=1e-9)
    np.testing.assert_allclose(ate.aligned_poses, gt.poses, atol=1e-9)


def test_zero_mean_uncorrelated_noise_gives_its_rms():
    # Cube corners with noise d * sign(x y z) along z: the noise sums to 0 and is uncorrelated with the
    # positions (sum of x * xyz = sum of y z = 0, ...), so H = sum p p^T = 8 I, the best fit is the
    # identity and every residual is exactly d: RMSE = mean = median = max = d.
    rng = np.random.default_rng(5)
    corners = cube_corners()
    d = 0.03
    signs = np.prod(corners, axis=1)
    gt = Trajectory(stamps(8), poses_at(corners, rng))
    est_poses = shifted(gt.poses, d * signs[:, None] * [0.0, 0.0, 1.0])
    T = random_pose(rng)
    ate = evaluate_ate(Trajectory(gt.stamps_ns, T @ est_poses), gt)
    assert ate.rmse_m == pytest.approx(d, abs=1e-12)
    assert ate.rmse_cm == pytest.approx(3.0, abs=1e-10)
    np.testing.assert_allclose(ate.errors_m, d, atol=1e-12)
    assert (ate.mean_m, ate.median_m, ate.max_m) == pytest.approx((d, d, d), abs=1e-12)


def test_constant_offset_on_a_subset_is_partly_absorbed_by_the_alignment():
    # Offset v on k = 2 of n = 8 poses, chosen at opposite corners so their centroid is the overall
    # centroid: the offset is uncorrelated with the positions, the rotation stays the identity and the
    # translation takes the mean offset (k/n) v. Residuals: (1 - k/n) v on the two, -(k/n) v on the six:
    # RMSE^2 = (k/n)(1 - k/n) |v|^2 = 3/16 |v|^2, mean = (2 * 3/4 + 6 * 1/4) / 8 |v| = 3/8 |v|.
    rng = np.random.default_rng(6)
    corners = cube_corners()
    v = np.array([0.02, -0.04, 0.04])  # |v| = 0.06
    subset = np.all(corners == 1, axis=1) | np.all(corners == -1, axis=1)
    assert subset.sum() == 2
    gt = Trajectory(stamps(8), poses_at(corners, rng))
    est = Trajectory(gt.stamps_ns, shifted(gt.poses, np.where(subset[:, None], v, 0.0)))
    ate = evaluate_ate(est, gt)
    assert ate.rmse_m == pytest.approx(np.sqrt(3) / 4 * 0.06, abs=1e-12)
    assert ate.mean_m == pytest.approx(3 / 8 * 0.06, abs=1e-12)
    assert ate.max_m == pytest.approx(0.75 * 0.06, abs=1e-12)
    np.testing.assert_allclose(ate.T_gt_est[:3, 3], -(2 / 8) * v, atol=1e-12)


def test_alternating_offset_on_a_straight_line():
    # Straight line along x with offsets +d, -d, -d, +d, ... along y. The pattern sums to 0 and is
    # symmetric about the middle, so it is uncorrelated with x: H = sum x_c x_c^T e_x e_x^T. Every
    # rotation about x (the line is collinear, so that rotation is undetermined) is optimal and keeps each
    # residual at distance d from the line point: RMSE = d exactly.
    rng = np.random.default_rng(7)
    n, d = 16, 0.01
    pattern = np.tile([1.0, -1.0, -1.0, 1.0], n // 4)
    line = np.c_[np.arange(n) * 0.1, np.zeros(n), np.zeros(n)]
    gt = Trajectory(stamps(n), poses_at(line, rng))
    est = Trajectory(gt.stamps_ns, random_pose(rng) @ shifted(gt.poses, d * pattern[:, None] * [0.0, 1.0, 0.0]))
    ate = evaluate_ate(est, gt)
    assert ate.rmse_m == pytest.approx(d, abs=1e-12)
    np.testing.assert_allclose(ate.errors_m, d, atol=1e-12)


def test_ate_without_alignment_is_the_raw_offset():
    rng = np.random.default_rng(8)
    gt = Trajectory(stamps(10), poses_at(rng.normal(size=(10, 3)), rng))
    est = Trajectory(gt.stamps_ns, shifted(gt.poses, [0.0, 0.05, 0.0]))
    assert evaluate_ate(est, gt, align=False).rmse_m == pytest.approx(0.05, abs=1e-12)
    assert evaluate_ate(est, gt, align=True).rmse_m < 1e-12


# ---------------------------------------------------------------------------------------------- association


def test_association_drops_unmatched_stamps_and_uses_each_gt_pose_once():
    rng = np.random.default_rng(9)
    # ground truth at 100.00, 100.10, ..., 100.90 s
    gt = Trajectory(stamps(10), poses_at(rng.normal(size=(10, 3)), rng))
    offsets_ms = {
        0: 0,  # exact
        1: 15,  # within 0.02 s
        2: 20,  # on the boundary: kept
        3: 21,  # just outside: dropped
        4: 50,  # half way: dropped
        5: -5,
        6: -30,  # dropped
    }
    est_ns = np.array(
        [gt.stamps_ns[i] + ms * 1_000_000 for i, ms in offsets_ms.items()]
        + [gt.stamps_ns[9] - 3_000_000, gt.stamps_ns[9] + 8_000_000],
        dtype=np.int64,
    )
    est = Trajectory(est_ns, np.tile(np.eye(4), (len(est_ns), 1, 1)))
    pair = associate_trajectories(est, gt)
    # two estimates near gt[9]: only the closer (-3 ms) keeps it
    np.testing.assert_array_equal(pair.stamps_ns, est_ns[[0, 1, 2, 5, 7]])
    np.testing.assert_array_equal(pair.gt_stamps_ns, gt.stamps_ns[[0, 1, 2, 5, 9]])
    np.testing.assert_array_equal(pair.gt_poses, gt.poses[[0, 1, 2, 5, 9]])
    assert (pair.n_est, pair.n_gt, len(pair)) == (9, 10, 5)
    ate = evaluate_ate(est, gt)
    assert ate.n_matched == 5


def test_too_few_matches_names_both_files(tmp_path):
    rng = np.random.default_rng(10)
    gt = Trajectory(stamps(10), poses_at(rng.normal(size=(10, 3)), rng))
    est = Trajectory(stamps(10, t0_s=500.0), gt.poses)  # another clock: nothing associates
    with pytest.raises(DatasetError) as err:
        evaluate_ate(est, gt, est_source=tmp_path / "est.txt", gt_source=tmp_path / "gt.txt")
    msg = str(err.value)
    assert "est.txt" in msg and "gt.txt" in msg and "only 0 of 10" in msg
    two = Trajectory(gt.stamps_ns[:2], gt.poses[:2])
    with pytest.raises(DatasetError, match="only 2 of 2"):
        evaluate_ate(two, gt)


# ---------------------------------------------------------------------------------------------- RPE


def test_rpe_of_a_perfect_trajectory_is_zero():
    rng = np.random.default_rng(11)
    gt = Trajectory(stamps(40), poses_at(rng.normal(size=(40, 3)), rng))
    est = Trajectory(gt.stamps_ns, random_pose(rng) @ gt.poses)  # RPE ignores the world frame
    for delta, unit in ((1, "frames"), (1.0, "s")):
        rpe = evaluate_rpe(est, gt, delta, unit)
        assert rpe.n_pairs > 0
        assert rpe.trans_max_m < 1e-9 and rpe.rot_max_deg < 1e-6


def test_rpe_with_one_translation_jump():
    # From frame k on, the estimate is moved by v in the world: only relative motions that straddle k
    # are wrong, each by E = Q_k^-1 T(v) Q_k, i.e. |trans(E)| = |v| and no rotation.
    rng = np.random.default_rng(12)
    n, k = 40, 17
    v = np.array([0.03, 0.0, -0.04])  # 5 cm
    gt = Trajectory(stamps(n, dt_s=0.1), poses_at(np.c_[np.arange(n) * 0.05, np.zeros(n), np.zeros(n)], rng))
    est_poses = gt.poses.copy()
    est_poses[k:, :3, 3] += v
    est = Trajectory(gt.stamps_ns, est_poses)

    per_frame = evaluate_rpe(est, gt, 1, "frames")
    expected = np.zeros(n - 1)
    expected[k - 1] = 0.05
    np.testing.assert_allclose(per_frame.trans_errors_m, expected, atol=1e-12)
    assert per_frame.trans_rmse_m == pytest.approx(0.05 / np.sqrt(n - 1), abs=1e-12)
    assert per_frame.trans_max_m == pytest.approx(0.05, abs=1e-12)
    assert per_frame.rot_max_deg < 1e-6

    # 1 s at 10 Hz: pairs (i, i + 10), 30 of them; the 10 with i in [k-10, k-1] straddle the jump
    per_second = evaluate_rpe(est, gt, 1.0, "s")
    np.testing.assert_array_equal(per_second.pairs, np.c_[np.arange(30), np.arange(30) + 10])
    assert per_second.trans_rmse_m == pytest.approx(0.05 * np.sqrt(10 / 30), abs=1e-12)
    assert np.count_nonzero(per_second.trans_errors_m > 1e-9) == 10


def test_rpe_with_a_rotation_jump_on_the_last_frame():
    rng = np.random.default_rng(13)
    n = 12
    gt = Trajectory(stamps(n), poses_at(rng.normal(size=(n, 3)), rng))
    est_poses = gt.poses.copy()
    est_poses[-1] = est_poses[-1] @ make_pose(Rotation.from_euler("z", 7.0, degrees=True).as_matrix(), np.zeros(3))
    rpe = evaluate_rpe(Trajectory(gt.stamps_ns, est_poses), gt, 1, "frames")
    expected = np.zeros(n - 1)
    expected[-1] = 7.0
    np.testing.assert_allclose(rpe.rot_errors_deg, expected, atol=1e-9)
    assert rpe.trans_max_m < 1e-12


def test_rpe_time_pairs_skip_gaps_in_the_data():
    # 10 Hz, 0..2 s, with 1.3..1.6 s missing: a pair needs a pose within 0.05 s of t + 1 s
    t_s = np.round(np.arange(21) * 0.1, 3)
    keep = ~((t_s > 1.25) & (t_s < 1.65))
    ns = np.round(t_s[keep] * NS).astype(np.int64)
    pairs = rpe_pairs(ns, 1.0, "s")
    starts = {round(t_s[keep][i], 3) for i, _ in pairs}
    assert starts == {0.0, 0.1, 0.2, 0.7, 0.8, 0.9, 1.0}
    for i, j in pairs:
        assert abs((ns[j] - ns[i]) / NS - 1.0) < 1e-9


def test_rpe_with_no_pairs_has_no_statistics():
    rng = np.random.default_rng(14)
    gt = Trajectory(stamps(5, dt_s=0.1), poses_at(rng.normal(size=(5, 3)), rng))
    pair = associate_trajectories(gt, gt)
    rpe = compute_rpe(pair, 1.0, "s")  # the trajectory lasts only 0.4 s
    assert rpe.n_pairs == 0 and rpe.trans_rmse_m is None and rpe.rot_rmse_deg is None


# ---------------------------------------------------------------------------------------------- real data


def test_tum_ground_truth_against_itself(tum_dir):
    from neb_slam_core.datasets import open_dataset

    ds = open_dataset(tum_dir)
    frames = [f for f in (ds[i] for i in range(0, len(ds), 10)) if f.T_world_cam is not None]
    assert len(frames) >= 25  # a frame without a ground-truth pose within 0.02 s has none
    rng = np.random.default_rng(15)
    T = random_pose(rng)
    est = Trajectory(np.array([f.stamp_ns for f in frames]), np.stack([T @ f.T_world_cam for f in frames]))
    gt = read_tum_trajectory(tum_dir / "groundtruth.txt")  # the full 100 Hz motion-capture file
    ate = evaluate_ate(est, gt, est_source="frames", gt_source=tum_dir / "groundtruth.txt")
    assert ate.n_matched == len(frames)
    assert ate.rmse_m < 1e-9
    rpe = evaluate_rpe(est, gt, 1.0, "s")
    assert rpe.n_pairs > 0 and rpe.trans_max_m < 1e-9
