"""Tracking against a fixed map: the Gauss-Newton model equals autograd's gradient of the paper's
objective, and both optimisers bring a perturbed pose back to the ground truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from neb_slam_core.config import TrackingConfig
from neb_slam_core.geometry.lie import PoseSet
from neb_slam_core.render.rays import sample_pixels
from neb_slam_core.render.renderer import objective
from neb_slam_core.render.sampling import sample_depths
from neb_slam_core.scene.freeze import frozen
from neb_slam_core.tracking import tracker as tracker_module
from neb_slam_core.tracking.gauss_newton import apply_step, evaluate_pose, normal_equations
from neb_slam_core.tracking.tracker import MotionPrior, Tracker, TrackingResult, fuse, motion_prior


def perturbed(T: np.ndarray, trans_m: np.ndarray, rot_deg: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(np.radians(rot_deg)).as_matrix() @ T[:3, :3]
    out[:3, 3] += trans_m
    return out


def pose_error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg)."""
    rot = Rotation.from_matrix(T[:3, :3] @ T_ref[:3, :3].T).magnitude()
    return float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3])), float(np.degrees(rot))


def test_apply_step_matches_the_pose_parameterisation():
    rng = np.random.default_rng(0)
    T = perturbed(np.eye(4), rng.normal(size=3), rng.normal(size=3) * 20)
    step = np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.3])
    pose = PoseSet(T)
    with torch.no_grad():
        pose.delta.copy_(torch.as_tensor(step, dtype=torch.float32)[None])
    np.testing.assert_allclose(apply_step(T, step), pose.numpy()[0], atol=1e-6)


@pytest.mark.parametrize(
    "observed_only, depth_noise",
    [(False, False), (True, False), (True, True)],
    ids=["whole-blocks", "observed-space", "depth-noise-weights"],
)
def test_normal_equations_equal_autograd_gradient_of_the_objective(fitted_small_map, observed_only, depth_noise):
    """``2 J^T W r`` is the gradient of the paper's objective in (omega, dt), and the cost is its value:
    autograd through the renderer is the reference (restricted to observed space or not, its rays' geometry
    weighed by their depth's noise or not, alike)."""
    fm = replace(fitted_small_map, render=replace(fitted_small_map.render, depth_noise_weights=depth_noise))
    frame = fm.held_out[2]
    T = perturbed(frame.T_world_cam, np.array([0.01, -0.005, 0.008]), np.array([0.5, -0.3, 0.2]))
    px = sample_pixels(frame, 512, np.random.default_rng(1), valid_depth_only=True)
    z = sample_depths(px.depth_m, fm.render.sampling, generator=torch.Generator().manual_seed(2))
    with frozen(fm.block_map):
        ev = evaluate_pose(fm.block_map, px, T, z, fm.render, None, observed_only)
        H, g = normal_equations(ev, fm.block_map, None)
        pose = PoseSet(T)
        rays = px.to_world(pose.matrices()[0])
        loss, _ = objective(
            fm.block_map, rays, fm.render, None, with_smoothness=False, z=z, observed_only=observed_only
        )
        loss.total.backward()
    reference = pose.delta.grad[0].double().numpy()
    assert ev.cost == pytest.approx(float(loss.total.detach()), rel=1e-5)
    # the model leaves out samples whose Jacobian is negligible: agreement to 1% of the gradient's size
    assert np.abs(2 * g - reference).max() <= 0.01 * np.abs(reference).max(), (2 * g, reference)
    assert np.all(np.linalg.eigvalsh(H) > 0)  # six observable directions: a well-posed step


@pytest.mark.parametrize("coarse_rays", [0, 256], ids=["one-stage", "coarse-stage"])
@pytest.mark.parametrize("start", [(0.02, 1.0), (0.04, 2.0)], ids=["2cm-1deg", "4cm-2deg"])
def test_gauss_newton_recovers_a_perturbed_pose(fitted_small_map, start, coarse_rays):
    fm = fitted_small_map
    cfg = TrackingConfig(n_rays=1024, iterations=8, method="gauss_newton", coarse_rays=coarse_rays)
    rng = np.random.default_rng(3)
    for frame in fm.held_out[:3]:
        direction = rng.normal(size=3)
        axis = rng.normal(size=3)
        T0 = perturbed(
            frame.T_world_cam, start[0] * direction / np.linalg.norm(direction), start[1] * axis / np.linalg.norm(axis)
        )
        result = Tracker(cfg, fm.render, seed=0).track(fm.block_map, frame, T0)
        trans, rot = pose_error(result.T_world_cam, frame.T_world_cam)
        assert trans < 0.003 and rot < 0.15, (trans, rot)
        assert result.iterations <= cfg.iterations * (2 if coarse_rays else 1)  # at most `iterations` a stage


def test_adam_reduces_the_error_of_a_perturbed_pose(fitted_small_map):
    """The paper's optimiser, at its learning rate for fast motion, brings a 2 cm error under a quarter of
    itself in 40 steps on each of three held-out frames (at about 1 cm per step Adam hovers around the
    minimum, so one frame's final error depends on the draw: three frames and a step count past the hovering
    make the check about the optimiser, not one draw; after 30 steps one of these frames still ends between
    0.05 and 0.27 of its error over six tracker seeds, after 40 all end below 0.11)."""
    fm = fitted_small_map
    cfg = TrackingConfig(n_rays=1024, iterations=40, lr=1e-2, method="adam")
    for frame in fm.held_out[:3]:
        T0 = perturbed(frame.T_world_cam, np.array([0.012, -0.012, 0.01]), np.array([0.0, 0.0, 0.0]))
        result = Tracker(cfg, fm.render, seed=0).track(fm.block_map, frame, T0)
        before = pose_error(T0, frame.T_world_cam)[0]
        assert pose_error(result.T_world_cam, frame.T_world_cam)[0] < 0.25 * before


def test_tracking_with_no_mapped_block_in_view_reports_no_valid_rays(fitted_small_map):
    fm = fitted_small_map
    frame = fm.held_out[0]
    far_away = frame.T_world_cam.copy()
    far_away[:3, 3] += np.array([100.0, 0.0, 0.0])
    for method in ("adam", "gauss_newton"):
        result = Tracker(replace(TrackingConfig(), method=method, iterations=2), fm.render).track(
            fm.block_map, frame, far_away
        )
        assert result.n_valid_rays == 0
        np.testing.assert_array_equal(result.T_world_cam, far_away)


def test_spatial_gradients_match_autograd(fitted_small_map):
    """The tracker's spatial gradients against autograd's gradients of the map's SDF and colours at
    samples along real rays: in closed form (the C++ path) equal up to float32 rounding; by forward
    differences (the other backends) equal up to the points whose step crosses a grid cell face of some
    level (about one in ten on this map: 16 levels, three axes)."""
    from neb_slam_core.tracking.gauss_newton import (
        forward_difference_gradients,
        spatial_gradients,
        spatial_gradients_autograd,
    )

    fm = fitted_small_map
    frame = fm.held_out[0]
    px = sample_pixels(frame, 256, np.random.default_rng(4), valid_depth_only=True)
    z = sample_depths(px.depth_m, fm.render.sampling, generator=torch.Generator().manual_seed(5))
    rays = px.to_world(torch.as_tensor(frame.T_world_cam, dtype=torch.float32))
    near_surface = (z - px.depth_m[:, None]).abs() < 0.1
    points = (rays.origins[:, None, :] + z[..., None] * rays.dirs[:, None, :])[near_surface]
    with frozen(fm.block_map):
        closed = spatial_gradients(fm.block_map, points, None)
        fd = forward_difference_gradients(fm.block_map, points, None)
        auto = spatial_gradients_autograd(fm.block_map, points, None)
    assert fm.block_map.spatial_gradients(points, None) is not None  # the closed form ran
    for k in range(4):
        err = (closed[k] - auto[k]).norm(dim=1) / auto[k].norm(dim=1).clamp(min=1e-6)
        assert float(err.max()) < 1e-3, (k, float(err.max()))
        # forward differences: exact within a cell, so most points agree to a fraction of a percent
        err = (fd[k] - auto[k]).norm(dim=1) / auto[k].norm(dim=1).clamp(min=1e-6)
        assert float(err.median()) < 0.005, (k, float(err.median()))
        # over all points (what enters the Gauss-Newton sums) the face crossings weigh little
        total = float((fd[k] - auto[k]).norm(dim=1).mean() / auto[k].norm(dim=1).mean())
        assert total < 0.05, (k, total)


def test_a_coarse_stage_of_all_the_rays_is_no_coarse_stage(fitted_small_map):
    """``coarse_rays`` at or above ``n_rays`` leaves one stage: the same pose to the bit."""
    fm = fitted_small_map
    frame = fm.held_out[0]
    T0 = perturbed(frame.T_world_cam, np.array([0.02, 0.0, -0.01]), np.array([0.0, 1.0, 0.5]))
    poses = []
    for coarse in (0, 512):
        cfg = TrackingConfig(n_rays=512, iterations=6, method="gauss_newton", coarse_rays=coarse)
        poses.append(Tracker(cfg, fm.render, seed=0).track(fm.block_map, frame, T0).T_world_cam)
    assert np.array_equal(poses[0], poses[1])


def test_a_proposed_step_below_the_stop_threshold_is_neither_evaluated_nor_taken(fitted_small_map, monkeypatch):
    """From 1 cm and half a degree off, the first Levenberg-Marquardt step moves the camera by about that
    much. With the stop threshold above it the stage ends at once: the start pose, no step counted, and the
    objective evaluated only at the start. With the default threshold the same start is corrected."""
    fm = fitted_small_map
    frame = fm.held_out[0]
    T0 = perturbed(frame.T_world_cam, np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.5, 0.0]))
    calls = []
    evaluate = tracker_module.evaluate_pose

    def counted(*args, **kwargs):
        calls.append(1)
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(tracker_module, "evaluate_pose", counted)
    stop_at_once = TrackingConfig(n_rays=512, iterations=6, method="gauss_newton", gn_stop_step_m=1.0)
    result = Tracker(stop_at_once, fm.render, seed=0).track(fm.block_map, frame, T0)
    assert np.array_equal(result.T_world_cam, T0) and result.iterations == 0 and len(calls) == 1
    calls.clear()
    default = replace(stop_at_once, gn_stop_step_m=TrackingConfig().gn_stop_step_m)
    result = Tracker(default, fm.render, seed=0).track(fm.block_map, frame, T0)
    assert result.iterations >= 1 and len(calls) == result.iterations + 1  # the start, then each step taken
    assert pose_error(result.T_world_cam, frame.T_world_cam)[0] < 0.5 * pose_error(T0, frame.T_world_cam)[0]


def test_the_coarse_stage_brings_a_far_start_closer_before_the_full_stage(fitted_small_map):
    """From 4 cm and 2 degrees off, the coarse stage (256 of 1024 rays) alone takes the pose to within a
    centimetre, so the stage on all rays starts inside its basin."""
    fm = fitted_small_map
    frame = fm.held_out[1]
    T0 = perturbed(frame.T_world_cam, np.array([0.0, 0.04, 0.0]), np.array([2.0, 0.0, 0.0]))
    coarse_only = TrackingConfig(n_rays=256, iterations=8, method="gauss_newton", gn_stop_step_m=2e-3)
    result = Tracker(coarse_only, fm.render, seed=0).track(fm.block_map, frame, T0)
    trans, rot = pose_error(result.T_world_cam, frame.T_world_cam)
    assert trans < 0.01 and rot < 0.5, (trans, rot)


def test_space_no_keyframe_saw_does_not_pull_a_pose_off_the_truth(small_scene):
    """A map made from the first frame alone (the engine's first map, 200 steps), tracked from the true
    poses of the next frames (4.8 to 19 cm away, towards space the first frame did not see): on the
    observed space alone the objective's minimum stays at the truth; with the whole block, the unfitted
    space in view pulls the pose towards where the first frame stood (measured: 4 to 10 mm)."""
    from neb_slam_core.config_io import load_config
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.slam import Slam

    ds = open_dataset(small_scene)
    cfg = load_config("ci")
    slam = Slam(cfg, T_world_first=ds[0].T_world_cam)
    slam.process(ds[0])
    errors = {}
    for observed_only in (True, False):
        tracker = Tracker(replace(cfg.tracking, observed_only=observed_only), cfg.render, seed=0)
        errors[observed_only] = [
            pose_error(tracker.track(slam.block_map, ds[k], ds[k].T_world_cam).T_world_cam, ds[k].T_world_cam)[0]
            for k in (1, 2, 3, 4)
        ]
    assert max(errors[True]) < 0.003, errors  # 3 mm, where the camera moves 48 mm a frame
    assert np.mean(errors[False]) > 3 * np.mean(errors[True]), errors


def test_the_pose_covariance_covers_the_tracking_error_and_stays_informative(fitted_small_map):
    """Tracking two held-out frames from 1.4 cm off with 8 different pixel draws each: every draw's error
    against the ground truth lies within 3 predicted standard deviations per axis, and the predicted
    deviation is at most 8 times the RMS error over the draws (the rays, not the residuals, count as the
    independent measurements, so the estimate errs on the safe side, by about 2 to 6 here)."""
    fm = fitted_small_map
    for frame in (fm.held_out[2], fm.held_out[4]):
        T0 = perturbed(frame.T_world_cam, np.array([0.01, -0.005, 0.008]), np.zeros(3))
        errors, sigmas = [], []
        for seed in range(8):
            r = Tracker(TrackingConfig(), fm.render, seed=seed).track(fm.block_map, frame, T0)
            assert r.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(r.covariance) > 0)
            errors.append(r.T_world_cam[:3, 3] - frame.T_world_cam[:3, 3])
            sigmas.append(np.sqrt(np.diag(r.covariance)[:3]))
        errors, sigmas = np.array(errors), np.array(sigmas)
        assert np.all(np.abs(errors) <= 3 * sigmas), (errors, sigmas)
        rms = np.sqrt((errors**2).mean(axis=0))
        assert np.all(sigmas.mean(axis=0) <= 8 * rms), (sigmas.mean(axis=0), rms)


def test_colour_scale_weighs_the_colour_loss_in_tracking(fitted_small_map):
    """``colour_scale`` 0 tracks on geometry alone: a frame whose colour is replaced by noise gets the same
    pose to the bit as with its own colour (the pixels and sample depths drawn do not depend on colour),
    and that pose is the ground truth's within the tolerance of the full objective; at 1 the noise moves
    the pose."""
    fm = fitted_small_map
    frame = fm.held_out[1]
    noise = np.random.default_rng(5).integers(0, 256, size=frame.rgb.shape, dtype=np.uint8)
    scrambled = replace(frame, rgb=noise)
    T0 = perturbed(frame.T_world_cam, np.array([0.015, -0.01, 0.005]), np.array([0.5, 0.0, -0.5]))
    poses = {}
    for scale in (0.0, 1.0):
        cfg = TrackingConfig(n_rays=1024, iterations=8, method="gauss_newton", colour_scale=scale)
        for label, f in (("own", frame), ("noise", scrambled)):
            poses[scale, label] = Tracker(cfg, fm.render, seed=0).track(fm.block_map, f, T0).T_world_cam
    assert np.array_equal(poses[0.0, "own"], poses[0.0, "noise"])
    trans, rot = pose_error(poses[0.0, "own"], frame.T_world_cam)
    assert trans < 0.003 and rot < 0.15, (trans, rot)
    assert not np.array_equal(poses[1.0, "own"], poses[1.0, "noise"])


def test_the_motion_prior_is_the_constant_velocity_error_of_the_accelerations():
    """At 30 frames/s, 2 m/s^2 leave the prediction ``a dt (dt + dt_prev) / 2 = 2/900`` m off (information
    ``(900/2)^2``); a frame after a dropped one (dt 1/15 s) ``2 * (1/15) * (1/10) / 2 = 1/150`` m. An
    acceleration of 0 leaves its part without information; both 0, or a time not positive, no prior."""
    cfg = TrackingConfig(motion_prior_m_s2=2.0, motion_prior_rad_s2=0.0)
    T_pred = perturbed(np.eye(4), np.array([0.1, 0.2, 0.3]), np.array([5.0, 0.0, 0.0]))
    prior = motion_prior(T_pred, 1 / 30, 1 / 30, cfg)
    np.testing.assert_allclose(prior.information, np.diag([450.0**2] * 3 + [0, 0, 0]), rtol=1e-12)
    np.testing.assert_array_equal(prior.T_world_cam, T_pred)
    dropped = motion_prior(T_pred, 1 / 15, 1 / 30, cfg)
    np.testing.assert_allclose(np.diag(dropped.information)[:3], 150.0**2, rtol=1e-12)
    angular = motion_prior(T_pred, 1 / 30, 1 / 30, replace(cfg, motion_prior_rad_s2=9.0))
    np.testing.assert_allclose(np.diag(angular.information)[3:], 100.0**2, rtol=1e-12)  # 9/900 rad = 0.01
    assert motion_prior(T_pred, 1 / 30, 1 / 30, TrackingConfig()) is None
    assert motion_prior(T_pred, 0.0, 1 / 30, cfg) is None and motion_prior(T_pred, 1 / 30, 0.0, cfg) is None


def test_the_prior_offset_is_the_tracking_update_from_the_prediction():
    """(tx, ty, tz, rx, ry, rz), the covariance's order: the tracking update (omega, dt) reordered."""
    T_pred = perturbed(np.eye(4), np.array([0.1, 0.2, 0.3]), np.array([5.0, -10.0, 20.0]))
    step = np.array([0.0, 0.0, 0.1, 0.01, -0.02, 0.03])  # 0.1 rad about the world z axis, then 1, -2, 3 cm
    prior = MotionPrior(T_pred, np.eye(6))
    T = apply_step(T_pred, step)
    np.testing.assert_allclose(prior.offset(T), np.concatenate([step[3:], step[:3]]), atol=1e-12)
    np.testing.assert_allclose(prior.moved(prior.offset(T)), T, atol=1e-12)


def test_fusing_weighs_the_tracked_pose_and_the_prediction_by_their_information():
    """A Kalman update worked by hand. The tracked pose is 4 mm along x and 0.02 rad about z off the
    prediction, with standard deviations 1 mm in x (information 1e6), 3 mm in y and z, 0.01 rad about
    each axis (1e4). A prior of information 3e6 in translation and 1e4 in rotation leaves x at
    ``1e6 / (1e6 + 3e6) = 1/4`` of its offset (1 mm) and the rotation at half (0.01 rad), with variances
    ``1 / 4e6`` and ``1 / 2e4``. Without a prior, or without a covariance, nothing changes."""
    T_pred = perturbed(np.eye(4), np.array([0.5, -0.2, 1.0]), np.array([10.0, 20.0, -30.0]))
    prior = MotionPrior(T_pred, np.diag([3e6] * 3 + [1e4] * 3))
    tracked_offset = np.array([0.004, 0.0, 0.0, 0.0, 0.0, 0.02])
    covariance = np.diag([1e-6, 9e-6, 9e-6, 1e-4, 1e-4, 1e-4])
    tracked = TrackingResult(prior.moved(tracked_offset), 0.5, 0.01, 1000, 4, covariance)
    fused = fuse(tracked, prior)
    np.testing.assert_allclose(prior.offset(fused.T_world_cam), [0.001, 0, 0, 0, 0, 0.01], atol=1e-12)
    np.testing.assert_allclose(np.diag(fused.covariance)[[0, 5]], [1 / 4e6, 1 / 2e4], rtol=1e-9)
    assert (fused.loss, fused.depth_residual_m, fused.n_valid_rays) == (0.5, 0.01, 1000)
    assert fuse(tracked, None) is tracked
    assert fuse(replace(tracked, covariance=None), prior).T_world_cam is tracked.T_world_cam


def test_a_prior_as_informative_as_the_frame_fuses_halfway(fitted_small_map):
    """On a map: a frame tracked from a prediction 1.5 cm and 0.6 degrees off, fused with a prior whose
    information equals the frame's, lands halfway between its tracked pose and the prediction; a prior
    ten times as informative keeps it within a tenth of that gap of the prediction."""
    fm = fitted_small_map
    cfg = TrackingConfig(n_rays=1024, iterations=8, method="gauss_newton")
    frame = fm.held_out[1]
    T_pred = perturbed(frame.T_world_cam, np.array([0.01, -0.008, 0.008]), np.array([0.0, 0.6, 0.0]))
    tracked = Tracker(cfg, fm.render, seed=0).track(fm.block_map, frame, T_pred)
    information = np.linalg.inv(tracked.covariance)
    gap = MotionPrior(T_pred, information).offset(tracked.T_world_cam)
    for scale, share in ((1.0, 0.5), (10.0, 1 / 11)):
        prior = MotionPrior(T_pred, scale * information)
        np.testing.assert_allclose(prior.offset(fuse(tracked, prior).T_world_cam), share * gap, atol=1e-9)
