"""Colour resampled to the depth image's capture time: hand-worked shifts on a flat wall."""

from __future__ import annotations

import numpy as np

from neb_slam_core.geometry.colour_timing import colour_at_depth_time, colour_offset_ns
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.types import Intrinsics, RgbdFrame

K = Intrinsics(100.0, 100.0, 32.0, 24.0, 64, 48)


def wall(depth_m: float = 2.0, extras: dict | None = None) -> RgbdFrame:
    """A fronto-parallel wall ``depth_m`` ahead whose colour is 3 x the column (red) and 5 x the row (green)."""
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[:, :, 0] = 3 * np.arange(64)[None, :]
    rgb[:, :, 1] = 5 * np.arange(48)[:, None]
    return RgbdFrame(rgb, np.full((48, 64), depth_m, np.float32), K, 0, extras=extras or {})


def test_a_sideways_move_shifts_the_colour_by_its_parallax():
    # the colour camera 2 cm right of the depth camera: a point 2 m ahead is fx * 0.02 / 2 = 1 px further
    # left in the colour image, so pixel u takes the colour of column u - 1
    f = wall()
    g = colour_at_depth_time(f, make_pose(np.eye(3), [0.02, 0.0, 0.0]))
    np.testing.assert_array_equal(g.rgb[10, 1:, 0], f.rgb[10, :-1, 0])
    np.testing.assert_array_equal(g.rgb[:, :, 1], f.rgb[:, :, 1])  # rows unchanged
    np.testing.assert_array_equal(g.rgb[10, 0, 0], f.rgb[10, 0, 0])  # off the image: the border colour
    np.testing.assert_array_equal(g.depth_m, f.depth_m)


def test_a_turn_shifts_the_colour_whatever_the_depth():
    # turned by atan(2 / 100) about the camera's y axis (the image's x towards the optical axis): every
    # point, near or far, moves 2 px in the colour image
    a = np.arctan2(2.0, 100.0)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    for depth in (0.5, 4.0):
        f = wall(depth)
        g = colour_at_depth_time(f, make_pose(R, [0.0, 0.0, 0.0]))
        # at the centre column (u = 32 = cx) the colour comes from u = 30: 3 * 30
        assert abs(int(g.rgb[24, 32, 0]) - 90) <= 1


def test_pixels_without_depth_keep_their_colour_and_no_motion_changes_nothing():
    f = wall()
    f.depth_m[:, :10] = 0.0
    g = colour_at_depth_time(f, make_pose(np.eye(3), [0.02, 0.0, 0.0]))
    np.testing.assert_array_equal(g.rgb[:, :10], f.rgb[:, :10])
    np.testing.assert_array_equal(colour_at_depth_time(f, np.eye(4)).rgb, f.rgb)


def test_colour_offset_from_the_loaders_stamps():
    assert colour_offset_ns(wall(extras={"colour_stamp_ns": 1_033, "depth_stamp_ns": 1_040})) == -7
    assert colour_offset_ns(wall()) == 0


def test_the_frontend_moves_the_colour_by_the_tracked_motion_over_the_offset():
    """The last two tracked frames 30 ms apart moved 6 cm sideways; a colour image taken 10 ms after its
    depth image was taken 2 cm further: 1 px at 2 m (fx 100), so pixel u takes the colour of u - 1."""
    from neb_slam_core.config_io import load_config
    from neb_slam_core.slam import Frontend, new_block_map

    f = wall(extras={"colour_stamp_ns": 1_010_000_000, "depth_stamp_ns": 1_000_000_000})
    for on in (True, False):
        cfg = load_config("ci", [f"tracking.colour_timing={str(on).lower()}"])
        fe = Frontend(cfg, new_block_map(cfg), np.eye(4))
        fe._tracked_motion = lambda: (make_pose(np.eye(3), [0.06, 0.0, 0.0]), 30_000_000)
        g = fe._colour_at_depth_time(f)
        if on:
            np.testing.assert_array_equal(g.rgb[10, 1:, 0], f.rgb[10, :-1, 0])
        else:
            assert g is f
    fe = Frontend(load_config("ci", ["tracking.colour_timing=true"]), new_block_map(load_config("ci")), np.eye(4))
    assert fe._colour_at_depth_time(f) is f  # no tracked motion yet: as taken
    plain = wall()
    assert fe._colour_at_depth_time(plain) is plain  # no capture times: as taken
