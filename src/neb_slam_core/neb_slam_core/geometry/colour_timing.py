"""The colour image of an RGB-D frame resampled to the depth image's capture time.

A sensor that does not synchronise its two cameras (TUM's Kinect v1: colour and depth up to 20 ms
apart) pairs a depth image with a colour image taken from a slightly different pose: at 0.4 m/s and
20 degrees/s, 20 ms move a point 2 m ahead by about 7 mm, several pixels. The losses compare the
colour and the depth of one pixel as if both saw the same point, so the colour term pulls the pose
towards where the camera was when the colour image was taken.

With the camera's motion from the depth image's time to the colour image's, ``M`` (``T_colour =
T_depth M``, e.g. from the constant-velocity model), a depth pixel's point ``X`` (camera axes at the
depth image's time) lies at ``pi(M^-1 X)`` in the colour image; sampling the colour there (bilinearly)
gives each depth pixel the colour of its own point. Pixels without depth keep their colour; a point
that falls outside the colour image takes the nearest border colour.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..types import COLOUR_STAMP, DEPTH_STAMP, RgbdFrame


def colour_offset_ns(frame: RgbdFrame) -> int:
    """How long after its depth image the frame's colour image was taken (ns; 0 when not known)."""
    colour, depth = frame.extras.get(COLOUR_STAMP), frame.extras.get(DEPTH_STAMP)
    return 0 if colour is None or depth is None else int(colour) - int(depth)


def colour_at_depth_time(frame: RgbdFrame, M: np.ndarray) -> RgbdFrame:
    """``frame`` (pinhole) with its colour resampled to the depth image's time, ``M`` ``(4, 4)`` the
    camera's motion from the depth image's time to the colour image's (module docstring)."""
    # float32, one image-sized array per axis, with the pixel coordinates as a row and a column that
    # broadcast: it runs on every tracked frame, where geometry.rays.backproject_pixels' float64 (N, 3)
    # points would cost several times as much
    K = frame.intrinsics
    h, w = frame.depth_m.shape
    u, v = np.arange(w, dtype=np.float32)[None, :], np.arange(h, dtype=np.float32)[:, None]
    z = frame.depth_m
    x, y = (u - np.float32(K.cx)) / np.float32(K.fx) * z, (v - np.float32(K.cy)) / np.float32(K.fy) * z
    # M^-1 X = R^T (X - t)
    R, t = np.asarray(M[:3, :3], np.float32), np.asarray(M[:3, 3], np.float32)
    dx, dy, dz = x - t[0], y - t[1], z - t[2]
    xc = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
    yc = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
    zc = R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz
    seen = (z > 0) & (zc > 1e-6)
    zc = np.where(seen, zc, np.float32(1.0))
    map_x = np.where(seen, np.float32(K.fx) * xc / zc + np.float32(K.cx), u)
    map_y = np.where(seen, np.float32(K.fy) * yc / zc + np.float32(K.cy), v)
    rgb = cv2.remap(frame.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return dataclasses.replace(frame, rgb=rgb)
