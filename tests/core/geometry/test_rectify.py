"""Lens undistortion of RGB-D frames: a raw (distorted) image of a known scene rectifies to its
pinhole image."""

from __future__ import annotations

import cv2
import numpy as np

from neb_slam_core.geometry.rectify import Rectifier, distortion_of
from neb_slam_core.types import Intrinsics, RgbdFrame

INTR = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
FR1 = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)  # TUM freiburg1


def plane_depth(x_n: np.ndarray, y_n: np.ndarray) -> np.ndarray:
    """Depth along pinhole rays (x_n, y_n, 1) of the tilted plane z = 2 + 0.5 x + 0.25 y (camera frame)."""
    # points t * (x, y, 1) with t = 2 + 0.5 t x + 0.25 t y  ->  t = 2 / (1 - 0.5 x - 0.25 y)
    return 2.0 / (1.0 - 0.5 * x_n - 0.25 * y_n)


def raw_frame() -> RgbdFrame:
    """What a camera with the fr1 distortion records of the plane: each raw pixel sees the pinhole ray of
    its undistorted position (OpenCV's undistortPoints inverts the lens model)."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    raw = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    norm = cv2.undistortPoints(raw, INTR.K, np.array(FR1))[:, 0, :]
    depth = plane_depth(norm[:, 0], norm[:, 1]).reshape(INTR.height, INTR.width).astype(np.float32)
    # colour encodes the normalised x coordinate, so geometry errors show up in colour as well
    rgb = np.repeat(np.clip(128 + 200 * norm[:, :1], 0, 255), 3, axis=1).reshape(INTR.height, INTR.width, 3)
    return RgbdFrame(rgb.astype(np.uint8), depth, INTR, 0, extras={"distortion": FR1})


def test_rectified_depth_is_the_pinhole_depth_of_the_plane():
    rectifier = Rectifier()
    frame = rectifier(raw_frame())
    assert distortion_of(frame) is None
    k = frame.intrinsics
    assert k == rectifier.intrinsics(INTR, FR1) and (k.width, k.height) == (INTR.width, INTR.height)
    assert k.fx > INTR.fx  # zoomed in slightly, so that no pixel falls outside the raw image
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    expected = plane_depth((u - k.cx) / k.fx, (v - k.cy) / k.fy)
    ok = frame.depth_m > 0
    assert ok.all()  # every rectified pixel was seen by the raw camera
    err = np.abs(frame.depth_m - expected)[ok]
    # nearest-neighbour resampling picks a raw pixel within half a pixel of the exact position: the
    # error is bounded by the depth change over one pixel step in u plus one in v
    dv, du = np.gradient(expected)
    assert np.all(err <= (np.abs(du) + np.abs(dv))[ok] + 1e-5)
    assert np.median(err) < 1e-3
    # without rectification the same pixels are off by centimetres near the borders
    assert np.abs(raw_frame().depth_m - expected).max() > 0.02
    colour_expected = np.clip(128 + 200 * (u - k.cx) / k.fx, 0, 255)
    assert np.median(np.abs(frame.rgb[..., 0][ok].astype(float) - colour_expected[ok])) <= 1.0


def test_frames_without_distortion_pass_unchanged():
    frame = raw_frame()
    frame.extras["distortion"] = (0.0,) * 5
    assert Rectifier()(frame) is frame
    assert Rectifier().intrinsics(INTR, (0.0,) * 5) == INTR
    frame.extras.pop("distortion")
    assert Rectifier()(frame) is frame
