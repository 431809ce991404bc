"""Gravity and the level frame: closed forms, a rendered floor, and the synthetic scene's first frame."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.geometry.gravity import floor_down, level_frame
from neb_slam_core.types import Intrinsics

K = Intrinsics(fx=100.0, fy=100.0, cx=79.5, cy=59.5, width=160, height=120)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def test_level_frame_of_an_optical_camera_is_the_rep103_body_frame():
    # a level camera (optical: y down, z forward) at (1, 2, 3): map x = camera z, y = -camera x, z = -camera y
    T = level_frame(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 2.0, 3.0]))
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], -R @ [1.0, 2.0, 3.0], atol=1e-12)


def test_level_frame_keeps_only_the_heading_of_a_tilted_forward():
    down = np.array([0.1, -0.2, -1.0])
    forward = np.array([1.0, 1.0, 0.7])  # pitched up
    T = level_frame(down, forward, np.zeros(3))
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ (down / np.linalg.norm(down)), [0.0, 0.0, -1.0], atol=1e-12)
    f_map = R @ forward
    assert f_map[1] == pytest.approx(0.0, abs=1e-12) and f_map[0] > 0  # heading along +x
    # forward along gravity: the yaw falls back to the world's x, still a rotation
    R2 = level_frame(down, -down, np.zeros(3))[:3, :3]
    np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-12)


def _camera_over_floor(pitch_deg: float, roll_deg: float, height_m: float, wall_m: float | None) -> tuple:
    """Depth of a camera ``height_m`` above the floor z = 0, pitched down and rolled; with ``wall_m`` a wall
    x = wall_m ahead. Returns the depth image and the true down in the camera frame."""
    p, r = -np.radians(pitch_deg), np.radians(roll_deg)
    # world z up; camera looks along +x: optical axes z = forward, x = right (-y world), y = down (-z world)
    R_level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # world <- level optical
    Rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])  # about x: down for p < 0
    Rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])  # roll about z
    R_wc = R_level @ Rx @ Rz
    o = np.array([0.0, 0.0, height_m])
    v, u = np.mgrid[0 : K.height, 0 : K.width]
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, dtype=float)], axis=-1)
    d_w = d_cam @ R_wc.T
    depth = np.full(u.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d_w[..., 2] < 0, -o[2] / d_w[..., 2], np.inf)
        depth = np.minimum(depth, t_floor)
        if wall_m is not None:
            depth = np.minimum(depth, np.where(d_w[..., 0] > 0, (wall_m - o[0]) / d_w[..., 0], np.inf))
    depth[~np.isfinite(depth) | (depth > 8.0)] = 0.0
    return depth, R_wc.T @ np.array([0.0, 0.0, -1.0])


@pytest.mark.parametrize("pitch, roll", [(25.0, 0.0), (35.0, 8.0), (15.0, -5.0)])
def test_floor_down_recovers_gravity_from_a_rendered_floor_and_wall(pitch, roll):
    depth, down = _camera_over_floor(pitch, roll, 1.3, wall_m=3.0)
    rng = np.random.default_rng(1)
    noisy = np.where(depth > 0, depth + rng.normal(0.0, 0.002, depth.shape), 0.0)
    found = floor_down(noisy, K, up_prior=np.array([0.0, -1.0, 0.0]))
    assert found is not None
    assert _angle_deg(found, down) < 0.5


def test_floor_down_finds_nothing_in_a_view_of_a_wall():
    # a level camera 1 m from a wall: the lowest ray (31 degrees down) meets the floor 2.2 m away, behind it
    depth, _ = _camera_over_floor(0.0, 0.0, 1.3, wall_m=1.0)
    assert depth.max() < 1.2
    assert floor_down(depth, K, up_prior=np.array([0.0, -1.0, 0.0])) is None


def test_floor_down_on_the_synthetic_scenes_first_frame(tmp_path):
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.synth.generate import generate

    ds = open_dataset(generate("small", tmp_path / "scene", n_frames=2, progress=False))
    f = ds[0]
    down_true = f.T_world_cam[:3, :3].T @ np.array([0.0, 0.0, -1.0])  # the scene is z-up
    found = floor_down(f.depth_m, f.intrinsics, up_prior=np.array([0.0, -1.0, 0.0]))
    assert found is not None
    assert _angle_deg(found, down_true) < 2.0
