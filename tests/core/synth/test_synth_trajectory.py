"""Camera trajectories: rotation convention, loop closure, smoothness, clearance."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.errors import ConfigError
from neb_slam_core.geometry.se3 import invert, is_rigid
from neb_slam_core.synth import generate as gen
from neb_slam_core.synth.trajectory import RouteCurve, TrajectorySpec, camera_rotation, make_trajectory


def test_camera_rotation_axes_by_hand():
    # yaw 0, pitch 0: looking along +x in a z-up world -> right = -y, down = -z, forward = +x
    R = camera_rotation(np.array([0.0]), np.array([0.0]))[0]
    assert np.allclose(R, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    # yaw 90 deg, pitch -30 deg: forward = (0, cos30, -sin30); right = (1, 0, 0)
    R = camera_rotation(np.array([np.pi / 2]), np.array([-np.pi / 6]))[0]
    assert np.allclose(R[:, 2], [0, np.cos(np.pi / 6), -0.5]) and np.allclose(R[:, 0], [1, 0, 0])
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)


def test_route_curve_interpolates_a_circle_at_constant_speed():
    ang = np.arange(12) * (2 * np.pi / 12)
    curve = RouteCurve(np.stack([np.cos(ang), np.sin(ang)], 1), closed=True)
    assert curve.length == pytest.approx(2 * np.pi, rel=2e-3)  # a periodic spline through 12 points of a unit circle
    xy, tangent, s = curve.sample(101)
    assert np.allclose(np.linalg.norm(xy, axis=1), 1.0, atol=2e-3)
    assert np.allclose(xy[0], xy[-1]) and np.allclose(xy[0], [1.0, 0.0])
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert step.std() / step.mean() < 2e-3
    assert np.allclose(np.einsum("ij,ij->i", tangent, xy), 0.0, atol=5e-3)  # tangent perpendicular to radius


def test_trajectory_stamps_and_fixed_heading():
    curve = RouteCurve(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]]), closed=True)
    spec = TrajectorySpec(
        n_frames=31,
        fps=30.0,
        yaw_amplitude_deg=0.0,
        pitch_deg=0.0,
        pitch_amplitude_deg=0.0,
        height_amplitude_m=0.0,
        height_m=1.5,
    )
    traj = make_trajectory(curve, spec, fixed_yaw_deg=90.0)
    assert traj.stamps_ns[0] == 1_000_000_000 and np.all(np.diff(traj.stamps_ns) == 33_333_333)
    assert np.allclose(traj.poses[:, :3, 2], [0.0, 1.0, 0.0])  # optical axis along +y throughout
    assert np.allclose(traj.positions[:, 2], 1.5)
    with pytest.raises(ConfigError, match="n_frames"):
        make_trajectory(curve, TrajectorySpec(n_frames=1))


def _relative_motion(poses):
    rel = np.einsum("nij,njk->nik", invert(poses[:-1]), poses[1:])
    step = np.linalg.norm(rel[:, :3, 3], axis=1)
    rot = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return step, rot


def test_default_trajectory_loops_smoothly_with_clearance(default_sequence):
    traj = default_sequence.trajectory
    assert len(traj) == 300
    assert all(is_rigid(T, tol=1e-9) for T in traj.poses)
    # a loop: the last pose is the first
    assert np.allclose(traj.poses[-1], traj.poses[0], atol=1e-9)
    step, rot = _relative_motion(traj.poses)
    # constant speed along the route, bounded per-frame motion, and no jumps in velocity
    assert step.max() < 0.08 and step.std() / step.mean() < 0.01
    assert rot.max() < 3.5
    accel = np.linalg.norm(np.diff(traj.positions, 2, axis=0), axis=1)
    assert accel.max() < 0.01  # < 1 cm change of per-frame displacement
    # camera height and looking mostly level
    assert np.all((traj.positions[:, 2] > 1.2) & (traj.positions[:, 2] < 1.6))
    assert np.abs(traj.poses[:, 2, 2]).max() < np.sin(np.radians(15))  # optical axis within 15 deg of level
    # clearance from every surface of the scene
    assert gen.camera_clearance(default_sequence.scene, traj.positions).min() >= 0.4
    # looks mostly along the direction of motion (the yaw variation is 12 deg on top of a smoothed heading)
    motion = np.diff(traj.positions[:, :2], axis=0)
    motion /= np.linalg.norm(motion, axis=1, keepdims=True)
    forward = traj.poses[:-1, :2, 2] / np.linalg.norm(traj.poses[:-1, :2, 2], axis=1, keepdims=True)
    assert np.median(np.einsum("ij,ij->i", motion, forward)) > np.cos(np.radians(20))


@pytest.mark.parametrize("name", ["large", "corridor"])
def test_other_presets_keep_clearance(name):
    seq = gen.build_sequence(gen.resolve_spec(name))
    assert gen.camera_clearance(seq.scene, seq.trajectory.positions).min() >= 0.4
    step, rot = _relative_motion(seq.trajectory.poses)
    assert step.max() < 0.08 and rot.max() < 3.5
    assert np.allclose(seq.trajectory.poses[-1], seq.trajectory.poses[0]) == (name == "large")
