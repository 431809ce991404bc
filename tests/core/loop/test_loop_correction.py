"""Loop correction: the paper's reprojection objective and the spreading of the correction."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neb_slam_core.geometry.se3 import invert, make_pose
from neb_slam_core.loop.correction import (
    _shared_correction,
    correction_size,
    fit_loop_pose,
    merge_correction,
    propagate_correction,
    reprojection_residuals,
    sample_pixels,
    strided_view,
)
from neb_slam_core.types import Intrinsics

K = Intrinsics(120.0, 120.0, 79.5, 59.5, 160, 120)
BOX_LO, BOX_HI = np.array([-2.0, -1.5, -1.2]), np.array([2.5, 1.3, 3.0])


def box_depth(T_world_cam: np.ndarray, k: Intrinsics = K) -> np.ndarray:
    """Depth (z in the camera) of the inside of an axis-aligned box, by ray casting its six walls."""
    v, u = np.mgrid[0 : k.height, 0 : k.width].astype(np.float64)
    dirs_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    d = dirs_cam @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (BOX_HI - o) / d
        t_lo = (BOX_LO - o) / d
    t = np.where(d > 0, t_hi, t_lo)  # the wall each axis reaches first, moving along the ray
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf).min(axis=1)  # z of dirs_cam is 1: t is the depth
    return t.reshape(k.height, k.width).astype(np.float32)


def pose(rotvec_deg, t) -> np.ndarray:
    return make_pose(Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix(), np.asarray(t, dtype=np.float64))


# two loop keyframes looking into a corner of the box (three walls: every degree of freedom constrained)
T_R1 = pose([5.0, -30.0, 0.0], [0.3, 0.2, 0.0])
T_R2 = pose([-4.0, -20.0, 3.0], [-0.2, 0.1, 0.4])
T_TRUE = pose([3.0, -25.0, 2.0], [0.1, 0.0, 0.3])


def views(stride: int = 1):
    return [strided_view(T, box_depth(T), K, stride) for T in (T_R1, T_R2)]


def current_pixels(n: int = 800):
    return sample_pixels(box_depth(T_TRUE), n, np.random.default_rng(0))


def test_residuals_vanish_at_the_true_pose_and_not_elsewhere():
    px, d = current_pixels()
    r, ok = reprojection_residuals(T_TRUE, px, d, K, views())
    assert ok.mean() > 0.8  # the keyframes see most of what the current one sees
    # exact geometry: what remains is the bilinear interpolation of depth (1/z is linear on a plane, z
    # is not), largest next to the box's edges, where it mixes two walls
    assert np.median(np.abs(r[ok])) < 1e-3 and np.percentile(np.abs(r[ok]), 99) < 0.05
    moved = pose([0.0, 0.0, 0.0], [0.03, 0.0, 0.0]) @ T_TRUE
    r2, ok2 = reprojection_residuals(moved, px, d, K, views())
    # 3 cm sideways: the walls facing x see it fully in the depth term, 120 px * 0.03 m / 2-4 m
    assert np.sqrt((r2[ok2] ** 2).sum(axis=1).mean()) > 0.5


def test_residual_jacobian_equals_central_differences():
    """The analytic Jacobian in the pose perturbation (phi, delta) against central differences of the
    residuals (steps of 1e-7: far inside a depth pixel's bilinear cell for almost every pixel)."""
    from neb_slam_core.geometry.se3 import so3_left_jacobian

    px, d = current_pixels(300)
    T = pose([0.4, -0.6, 0.3], [0.01, -0.02, 0.015]) @ T_TRUE
    r, ok, J = reprojection_residuals(T, px, d, K, views(2), jacobian=True)
    h = 1e-7
    numeric = np.zeros_like(J)
    for i in range(6):
        step = np.zeros(6)
        step[i] = h
        moved = [T.copy(), T.copy()]
        for sign, M in zip((1.0, -1.0), moved):
            M[:3, :3] = Rotation.from_rotvec(sign * step[:3]).as_matrix() @ T[:3, :3]
            M[:3, 3] += sign * step[3:]
        (r_plus, ok_plus), (r_minus, ok_minus) = (reprojection_residuals(M, px, d, K, views(2)) for M in moved)
        numeric[..., i] = (r_plus - r_minus) / (2 * h)
        ok &= ok_plus & ok_minus
    scale = np.abs(numeric[ok]).max(axis=(0, 1))  # per pose component
    err = np.abs(J[ok] - numeric[ok]) / scale
    # a few pixels' steps cross a bilinear cell face, where the slope jumps
    assert np.mean(err.max(axis=(1, 2)) < 1e-6) > 0.99 and ok.sum() > 400
    assert np.all(J[~ok] == 0)
    # the left Jacobian: exp(w + d) = exp(J_l d) exp(w) to second order
    w, dw = np.array([0.3, -0.5, 0.8]), 1e-6 * np.array([1.0, 2.0, -1.5])
    lhs = Rotation.from_rotvec(w + dw).as_matrix()
    rhs = Rotation.from_rotvec(so3_left_jacobian(w) @ dw).as_matrix() @ Rotation.from_rotvec(w).as_matrix()
    assert np.abs(lhs - rhs).max() < 1e-11
    np.testing.assert_allclose(so3_left_jacobian(np.array([1e-6, 0.0, 0.0])), np.eye(3), atol=1e-6)


@pytest.mark.parametrize("stride", [1, 2])
def test_fit_recovers_the_pose_from_a_perturbed_start(stride):
    px, d = current_pixels()
    start = pose([1.0, -1.5, 0.5], [0.04, -0.03, 0.05]) @ T_TRUE  # ~7 cm and ~2 degrees off
    fit = fit_loop_pose(start, px, d, K, views(stride))
    cm, deg = correction_size(T_TRUE, fit.T_world_cam)
    assert cm < 0.05 and deg < 0.02, (cm, deg)
    assert fit.rms_px < 0.05 < fit.rms_px_start and fit.n_valid > 0.8 * 2 * len(px)


def test_strided_view_scales_the_camera():
    v = strided_view(np.eye(4), box_depth(T_R1), K, 2)
    assert v.depth_m.shape == (60, 80) and v.intrinsics.width == 80 and v.intrinsics.height == 60
    # full-resolution pixel (2i, 2j) is strided pixel (i, j): same depth, same ray
    assert v.depth_m[10, 20] == box_depth(T_R1)[20, 40]
    assert v.intrinsics.fx == 60.0 and v.intrinsics.cx == 79.5 / 2


def test_propagation_undoes_a_uniform_turning_drift_exactly():
    """Ground truth: 20 steps of 50 cm straight ahead. Tracking turned 1 degree too far at every step,
    so the estimate curls (43 cm off at worst). Given the true end pose, the pose graph puts every
    keyframe back on the ground truth: the correction every edge needs is the same small turn, the
    least-squares solution of the chain. Rotating all keyframes by a share of the end's correction
    about one point (the starting guess) leaves them tens of centimetres off."""
    n = 20
    gt, est = [np.eye(4)], [np.eye(4)]
    for _ in range(n):
        gt.append(gt[-1] @ pose([0, 0, 0], [0.5, 0, 0]))
        est.append(est[-1] @ pose([0, 0, 1.0], [0.5, 0, 0]))
    gt, est = np.stack(gt), np.stack(est)
    out = propagate_correction(est, 0, n, gt[-1])
    np.testing.assert_allclose(out[:, :3, 3], gt[:, :3, 3], atol=1e-4)
    for k in range(n + 1):
        assert correction_size(gt[k], out[k])[1] < 1e-3
    shared = _shared_correction(est, 0, n, gt[-1])
    assert np.abs(shared[:, :3, 3] - gt[:, :3, 3]).max() > 0.3


def test_registration_edges_send_the_correction_to_where_tracking_drifted():
    """A straight chain of 10 steps of 20 cm along x; tracking got step 4 wrong by 5 cm (everything after
    it is 5 cm further along), every other step right. Registrations measure all 10 steps right. With the
    end put back at its true place, the pose graph is a weighted least-squares chain (the rotations stay
    zero: the disagreement is along the chain): the two edges of step 4, weights w' (tracked, 25 cm) and
    w (registered, 20 cm), act as one edge of precision w'^2 + w^2 that wants 5 cm x w'^2 / (w'^2 + w^2)
    too much; every other step is two agreeing edges of precision 2 w^2; the excess comes off each step
    in proportion to 1 / precision. Without the registrations the whole 5 cm is spread by path length
    and the keyframes before the wrong step move most."""
    n, s, m, delta = 10, 0.2, 4, 0.05
    gt = np.stack([pose([0, 0, 0], [s * k, 0.0, 0.0]) for k in range(n + 1)])
    tracked = gt.copy()
    tracked[m + 1 :, 0, 3] += delta
    registrations = {(k, k + 1): invert(gt[k]) @ gt[k + 1] for k in range(n)}
    registrations[(0, 5)] = pose([0, 0, 30.0], [9.0, 9.0, 9.0])  # starts outside the chain (1..n): ignored
    out = propagate_correction(tracked, 1, n, gt[-1], registrations)

    w2, w2_wrong = 1.0 / (s + 0.01), 1.0 / (s + delta + 0.01)  # squared weights: 1 / (length + 1 cm)
    precision = np.full(n, 2 * w2)
    precision[m] = w2 + w2_wrong
    want = np.full(n, s)
    want[m] += delta * w2_wrong / (w2 + w2_wrong)
    free = np.arange(1, n)  # steps 1..n-1 lie between the held ends
    steps = want.copy()
    steps[free] -= (want[free].sum() - s * (n - 1)) * (1 / precision[free]) / (1 / precision[free]).sum()
    expected_x = np.concatenate([[0.0], np.cumsum(steps)])
    np.testing.assert_allclose(out[:, 0, 3], expected_x, atol=1e-5)
    np.testing.assert_allclose(out[:, 1:3, 3], 0.0, atol=1e-6)
    assert max(correction_size(gt[k], out[k])[1] for k in range(n + 1)) < 1e-4

    error_with = np.abs(out[:, 0, 3] - gt[:, 0, 3]).max()
    plain = propagate_correction(tracked, 1, n, gt[-1])
    error_without = np.abs(plain[:, 0, 3] - gt[:, 0, 3]).max()
    assert error_with < 0.6 * error_without, (error_with, error_without)


def test_propagation_holds_the_start_and_moves_the_rest_with_the_end():
    # keyframes every 1 m along x (then one more after the loop's end); the end is moved 40 cm along y
    poses = np.stack([pose([0, 0, 0], [float(i), 0.0, 0.0]) for i in range(7)])
    end_new = pose([0, 0, 0], [5.0, 0.4, 0.0])
    out = propagate_correction(poses, 1, 5, end_new)
    np.testing.assert_array_equal(out[:2], poses[:2])  # up to the loop's older end: held
    np.testing.assert_array_equal(out[5], end_new)  # the fitted pose, exactly
    np.testing.assert_allclose(out[6], pose([0, 0, 0], [6.0, 0.4, 0.0]), atol=1e-12)  # rigidly with the end
    lateral = out[1:6, 1, 3]
    assert np.all(np.diff(lateral) > 0) and np.all(np.abs(out[2:5, 0, 3] - [2, 3, 4]) < 0.01)
    # the chain is symmetric about its middle: the middle keyframe takes half the correction
    assert np.isclose(out[3, 1, 3], 0.2, atol=0.05)


def test_propagation_keeps_relative_poses_near_the_end():
    rng = np.random.default_rng(1)
    poses = [np.eye(4)]
    for _ in range(20):  # a wandering chain of 20 cm steps
        poses.append(poses[-1] @ pose(rng.normal(0, 3, 3), rng.normal(0, 0.12, 3)))
    poses = np.stack(poses)
    end_new = pose([0.0, 4.0, 0.0], [0.05, 0.0, 0.1]) @ poses[20]
    out = propagate_correction(poses, 0, 20, end_new)
    # the 4 degrees and 11 cm are spread over 20 edges: none changes by more than a fraction of them
    changes = [correction_size(invert(poses[k - 1]) @ poses[k], invert(out[k - 1]) @ out[k]) for k in range(1, 21)]
    assert max(cm for cm, _ in changes) < 2.0 and max(deg for _, deg in changes) < 0.6, changes
    assert sum(deg for _, deg in changes) > 3.0  # together they make up the turn
    np.testing.assert_allclose(out[20], end_new, atol=1e-12)
    with pytest.raises(ValueError, match="start_id"):
        propagate_correction(poses, 5, 5, end_new)


def test_merge_correction_moves_later_keyframes_rigidly():
    poses = np.stack([pose([0, 0, 0], [float(i), 0.0, 0.0]) for i in range(6)])
    corrected = np.stack([pose([0, 0, 0], [2.0, 0.1, 0.0]), pose([0, 0, 10.0], [3.0, 0.2, 0.0])])
    out = merge_correction(poses, 2, corrected)
    assert np.allclose(out[:2], poses[:2]) and np.allclose(out[2:4], corrected)
    # keyframes 4 and 5 keep their pose relative to keyframe 3
    for k in (4, 5):
        assert np.allclose(invert(out[3]) @ out[k], invert(poses[3]) @ poses[k])
    with pytest.raises(ValueError, match="not after the first"):
        merge_correction(poses, 0, corrected)
    with pytest.raises(ValueError):
        merge_correction(poses, 5, corrected)
