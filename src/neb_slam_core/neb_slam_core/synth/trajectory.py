"""Smooth camera trajectories along a floor plan's route.

The route waypoints are interpolated by a C2 cubic spline in the plane (periodic for a loop, natural
for an open route), parameterised by chord length, and resampled at equal arc length: the camera
moves at constant speed, so consecutive frames are equally spaced and a constant-velocity motion
model predicts them well (the spline's acceleration is continuous).

Orientation: the camera looks along the direction of motion (or, when the floor plan asks for it, at a
fixed mean heading), plus gentle sinusoidal yaw, pitch and height variations whose periods fit a
whole number of times into a loop, so a loop's last pose equals its first.

Poses are ``T_world_cam`` with OpenCV optical axes (x right, y down, z forward) in a z-up world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d

from ..errors import ConfigError
from ..io.trajectory import Trajectory


@dataclass(frozen=True)
class TrajectorySpec:
    """How the camera moves along the route.

    Attributes:
        n_frames: number of frames, spread at equal arc length over the whole route (a loop's last
            frame is back at the start).
        fps: frame rate of the stamps (stamps are ``start_stamp_ns + i * round(1e9 / fps)``).
        start_stamp_ns: stamp of the first frame (not 0, which ROS tools read as "unset").
        height_m: mean camera height above the floor.
        height_amplitude_m: amplitude of the height variation.
        pitch_deg: mean pitch (negative: looking down).
        pitch_amplitude_deg, yaw_amplitude_deg: amplitudes of the sinusoidal variations.
        heading_smoothing_m: the direction of travel the camera looks along is averaged over this
            length of route (Gaussian standard deviation), which spreads each turn and lowers the
            peak rotation per frame.
        wave_length_m: approximate period, along the route, of the yaw variation (pitch and height use
            longer periods so the three do not move in lock-step).
        min_clearance_m: every camera centre keeps at least this distance from the scene's surfaces
            (checked by the generator).
    """

    n_frames: int = 300
    fps: float = 30.0
    start_stamp_ns: int = 1_000_000_000
    height_m: float = 1.4
    height_amplitude_m: float = 0.1
    pitch_deg: float = -8.0
    pitch_amplitude_deg: float = 5.0
    yaw_amplitude_deg: float = 12.0
    wave_length_m: float = 5.0
    heading_smoothing_m: float = 0.5
    min_clearance_m: float = 0.4

    def validate(self) -> None:
        if self.n_frames < 2:
            raise ConfigError(f"TrajectorySpec.n_frames: expected at least 2 frames, got {self.n_frames}")
        if not self.fps > 0:
            raise ConfigError(f"TrajectorySpec.fps: expected > 0, got {self.fps}")
        if not (
            self.height_m - abs(self.height_amplitude_m) >= 0.3 and self.height_m + abs(self.height_amplitude_m) <= 2.0
        ):
            raise ConfigError(
                f"TrajectorySpec.height_m: camera height must stay within 0.3..2.0 m, got "
                f"{self.height_m} +/- {self.height_amplitude_m}"
            )


class RouteCurve:
    """A C2 cubic spline through 2D waypoints, evaluated by arc length.

    Args:
        waypoints_xy: ``(M, 2)`` metres; for a loop the first point is not repeated at the end.
        closed: a periodic spline through the waypoints and back to the first.
    """

    def __init__(self, waypoints_xy: np.ndarray, closed: bool):
        pts = np.asarray(waypoints_xy, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 3:
            raise ConfigError(f"route: need at least 3 waypoints, got {len(pts)}")
        if closed:
            pts = np.concatenate([pts, pts[:1]])
        chord = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        if (chord < 1e-6).any():
            raise ConfigError("route: two consecutive waypoints coincide")
        knots = np.concatenate([[0.0], np.cumsum(chord)])
        self.closed = closed
        self._spline = CubicSpline(knots, pts, bc_type="periodic" if closed else "natural")
        # arc length table: dense samples of the spline parameter (the library gives no arc-length
        # parameterisation, so it is tabulated and inverted by interpolation)
        n = max(2000, int(knots[-1] / 0.002))
        self._t = np.linspace(0.0, knots[-1], n)
        speed = np.linalg.norm(self._spline(self._t, 1), axis=1)
        self._s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(self._t))])
        self.length = float(self._s[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc lengths ``(N,)`` -> positions ``(N, 2)`` and unit tangents ``(N, 2)``."""
        t = np.interp(np.asarray(s, dtype=np.float64), self._s, self._t)
        d = self._spline(t, 1)
        return self._spline(t), d / np.linalg.norm(d, axis=1, keepdims=True)

    def heading(self, s: np.ndarray, smooth_m: float = 0.0) -> np.ndarray:
        """Direction of travel (radians from +x towards +y) at arc lengths ``s`` ``(N,)``, averaged over
        a Gaussian window of ``smooth_m`` metres (standard deviation) so the camera turns before and
        after a bend rather than only inside it."""
        s = np.asarray(s, dtype=np.float64)
        if smooth_m <= 0:
            tangent = self.at(s)[1]
            return np.arctan2(tangent[:, 1], tangent[:, 0])
        step = 0.01
        n_dense = max(int(np.ceil(self.length / step)), 16)
        s_dense = np.linspace(0.0, self.length, n_dense, endpoint=not self.closed)
        tangent = self.at(s_dense)[1]
        sigma = smooth_m / (s_dense[1] - s_dense[0])
        mode = "wrap" if self.closed else "nearest"
        avg = np.stack([gaussian_filter1d(tangent[:, k], sigma, mode=mode) for k in (0, 1)], axis=1)
        yaw_dense = np.unwrap(np.arctan2(avg[:, 1], avg[:, 0]))
        if self.closed:  # periodic interpolation: append the first sample one period later
            s_dense = np.append(s_dense, self.length)
            yaw_dense = np.append(
                yaw_dense, yaw_dense[0] + 2 * np.pi * np.round((yaw_dense[-1] - yaw_dense[0]) / (2 * np.pi))
            )
        return np.interp(s, s_dense, yaw_dense)

    def sample(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` points at equal arc length from start to end (a loop's last point is its first).

        Returns positions ``(n, 2)``, unit tangents ``(n, 2)`` and arc lengths ``(n,)``.
        """
        s = np.linspace(0.0, self.length, n)
        xy, tangent = self.at(s)
        if self.closed:  # exact closure, not up to the interpolation's rounding
            xy[-1], tangent[-1] = xy[0], tangent[0]
        return xy, tangent, s


def route_curve(waypoints_xy: np.ndarray, closed: bool) -> RouteCurve:
    return RouteCurve(waypoints_xy, closed)


def camera_rotation(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """World-from-camera rotations ``(N, 3, 3)`` for headings ``yaw`` (from +x towards +y) and ``pitch``
    (positive: up), radians, in a z-up world; the camera's columns are (right, down, forward)."""
    yaw, pitch = np.broadcast_arrays(np.asarray(yaw, np.float64), np.asarray(pitch, np.float64))
    f = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1)
    r = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)  # f x up, normalised
    d = np.cross(f, r)
    return np.stack([r, d, f], axis=-1)


def make_trajectory(
    curve: RouteCurve, spec: TrajectorySpec, floor_z: float = 0.0, fixed_yaw_deg: float | None = None
) -> Trajectory:
    """Poses along ``curve``: ``spec.n_frames`` frames at constant speed, stamped at ``spec.fps``."""
    spec.validate()
    n = spec.n_frames
    xy, _, s = curve.sample(n)
    phase = s / curve.length  # 0..1 along the route

    def cycles(period_m: float) -> float:
        c = curve.length / period_m
        return float(max(1, round(c))) if curve.closed else c

    wave_yaw = np.sin(2 * np.pi * cycles(spec.wave_length_m) * phase)
    wave_pitch = np.sin(2 * np.pi * cycles(1.7 * spec.wave_length_m) * phase + 0.7)
    wave_height = np.sin(2 * np.pi * cycles(2.3 * spec.wave_length_m) * phase + 1.9)

    if fixed_yaw_deg is None:
        yaw = curve.heading(s, spec.heading_smoothing_m)
    else:
        yaw = np.full(n, np.deg2rad(fixed_yaw_deg))
    yaw = yaw + np.deg2rad(spec.yaw_amplitude_deg) * wave_yaw
    pitch = np.deg2rad(spec.pitch_deg + spec.pitch_amplitude_deg * wave_pitch)
    z = floor_z + spec.height_m + spec.height_amplitude_m * wave_height

    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = camera_rotation(yaw, pitch)
    poses[:, :2, 3] = xy
    poses[:, 2, 3] = z
    if curve.closed:
        poses[-1] = poses[0]
    period_ns = int(round(1e9 / spec.fps))
    stamps = spec.start_stamp_ns + np.arange(n, dtype=np.int64) * period_ns
    return Trajectory(stamps, poses)
