"""Lens undistortion of RGB-D frames (pinhole images for the engine).

The engine's rays assume a pinhole camera. Sensors such as TUM's freiburg1 Kinect publish raw images
with ``plumb_bob`` distortion (k1, k2, p1, p2, k3): for fr1 a pixel near the corner is 20 px away from
its pinhole position, which bends walls by centimetres and makes tracking drift. :class:`Rectifier`
resamples such frames onto a pinhole camera of the same image size: colour bilinearly, depth by
nearest neighbour (interpolating depth across an occlusion edge would invent surfaces between
foreground and background). The pinhole camera is OpenCV's optimal new camera matrix with alpha 0:
slightly zoomed so that every output pixel was seen by the raw camera (no black corners, which would
otherwise be learnt as black surfaces by the colour loss). The frame's intrinsics become that
camera's. The remap tables are computed once per camera.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..types import Intrinsics, RgbdFrame


def distortion_of(frame: RgbdFrame) -> np.ndarray | None:
    """The frame's ``plumb_bob`` coefficients (float64, 4/5/8 values) if any is non-zero, else None."""
    d = frame.extras.get("distortion")
    if d is None:
        return None
    d = np.asarray(d, dtype=np.float64).reshape(-1)
    return d if d.size and np.any(d != 0.0) else None


class Rectifier:
    """Undistorts frames whose ``extras["distortion"]`` is non-zero; other frames pass unchanged."""

    def __init__(self):
        self._maps: dict[tuple, tuple[np.ndarray, np.ndarray, Intrinsics]] = {}

    def _maps_for(self, intr: Intrinsics, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
        key = (intr.as_tuple(), tuple(dist.tolist()))
        if key not in self._maps:
            size = (intr.width, intr.height)
            K, _ = cv2.getOptimalNewCameraMatrix(intr.K, dist, size, 0.0, size)
            mx, my = cv2.initUndistortRectifyMap(intr.K, dist, None, K, size, cv2.CV_32FC1)
            pinhole = Intrinsics(
                float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), intr.width, intr.height
            )
            self._maps[key] = (mx, my, pinhole)
        return self._maps[key]

    def intrinsics(self, intr: Intrinsics, distortion) -> Intrinsics:
        """The pinhole camera that frames of camera ``intr`` with ``distortion`` are rectified to."""
        d = np.asarray(distortion, dtype=np.float64).reshape(-1)
        return self._maps_for(intr, d)[2] if np.any(d != 0.0) else intr

    def __call__(self, frame: RgbdFrame) -> RgbdFrame:
        dist = distortion_of(frame)
        if dist is None:
            return frame
        mx, my, pinhole = self._maps_for(frame.intrinsics, dist)
        rgb = cv2.remap(frame.rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        depth = cv2.remap(frame.depth_m, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        extras = dict(frame.extras, distortion=tuple(0.0 for _ in dist))
        return dataclasses.replace(frame, rgb=rgb, depth_m=depth.astype(np.float32), intrinsics=pinhole, extras=extras)
