"""Frames and TF of the tracking nodes (``tracker``, ``slam``), after REP-103 and REP-105.

The engine works in its world frame: the first frame's camera (optical axes: z forward, y down), or the
first ground-truth pose's frame. What the nodes publish is in ``map_frame``, a level frame: z up, x along
the robot's first heading, origin at the first position of ``base_frame``. :func:`map_alignment` fixes
``T_map_world`` at the first frame, from one of three sources of gravity (``gravity``):

- ``extrinsic``: down is -z of ``base_frame`` at the first frame (``base_to_camera`` says how the camera
  sits on the base): right for a robot that starts on level ground. ``map`` is then the first base pose.
- ``floor``: the floor's normal in the first depth image (:func:`~neb_slam_core.geometry.gravity.floor_down`,
  searched within 45 degrees of the extrinsic's up): right for a hand-held or tilted camera that sees the
  floor; without a floor in view it falls back to ``extrinsic`` with a warning.
- ``vector``: ``gravity_vector``, down in the first camera's optical frame (an accelerometer's reading at
  rest, negated, say).

:class:`TfOutput` publishes, stamped with each frame's image stamp, ``map -> odom -> base`` on ``/tf`` (with
``odom_frame`` empty: ``map -> base``) and ``base -> camera`` once on ``/tf_static``. The split is rtabmap's:
``odom -> base`` is continuous (each frame adds the motion tracking measured since the previous frame),
``map -> odom`` takes the jumps of map optimisation and loop closure. A robot with its own odometry
publishes ``odom -> base`` itself: with ``odom_from_tf`` the node publishes only ``map -> odom``, the
transform that makes the robot's ``odom -> base`` at the image's stamp (interpolated between the two
nearest on ``/tf``) end where tracking put the base. The camera frame is ``camera_frame``, or the colour
image's ``header.frame_id``.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tf2_msgs.msg import TFMessage

from neb_slam_core.geometry.gravity import floor_down, level_frame
from neb_slam_core.geometry.se3 import invert, pose_from_tum
from neb_slam_core.types import RgbdFrame
from neb_slam_ros import conversions, qos
from neb_slam_ros.params import require

#: a camera optical frame (z forward, x right, y down) on a base at its origin, looking along the base's
#: x (x y z qx qy qz qw): REP-103's rotation between a body frame and an optical frame
OPTICAL_ON_BASE = (0.0, 0.0, 0.0, -0.5, 0.5, -0.5, 0.5)

GRAVITY_SOURCES = ("extrinsic", "floor", "vector")

#: the engine's world frame, named by the topics between the nodes whose poses are the engine's
#: (``keyframe/pose``, ``loop_closure``); ``T_map_world`` places it in ``map_frame``
WORLD_FRAME = "neb_slam_world"


@dataclass(frozen=True)
class FrameOptions:
    """The frame parameters of the tracking nodes (see the module docstring)."""

    map_frame: str = "map"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    camera_frame: str = ""
    base_to_camera: tuple = OPTICAL_ON_BASE
    gravity: str = "extrinsic"
    gravity_vector: tuple = (0.0, 1.0, 0.0)
    publish_tf: bool = True
    odom_from_tf: bool = False

    PARAMETER_DOCS = {
        "map_frame": "frame of the published poses, path, blocks and mesh: level, z up (REP-103)",
        "odom_frame": "frame between map and base on /tf (map -> odom jumps with corrections, odom -> base is "
        "continuous); empty: publish map -> base",
        "base_frame": "the robot's body frame",
        "camera_frame": "the camera's optical frame; empty: the colour image's header.frame_id",
        "base_to_camera": "pose of the camera's optical frame in base_frame: x y z qx qy qz qw (default: at the "
        "origin, looking along x)",
        "gravity": "where the map's up comes from: extrinsic (base z up at the first frame), floor (the first "
        "depth image's floor), vector (gravity_vector)",
        "gravity_vector": "with gravity vector: down in the first camera's optical frame",
        "publish_tf": "publish map -> odom -> base on /tf and base -> camera on /tf_static",
        "odom_from_tf": "the robot's odometry publishes odom_frame -> base_frame on /tf: publish only map -> odom, "
        "from it",
    }

    def check(self) -> None:
        for name in ("map_frame", "base_frame"):
            require(bool(getattr(self, name)), name, "a frame name", getattr(self, name))
        frames = [f for f in (self.map_frame, self.odom_frame, self.base_frame, self.camera_frame) if f]
        require(len(set(frames)) == len(frames), "map_frame", "frame names that differ from each other", frames)
        q = np.asarray(self.base_to_camera, dtype=np.float64)
        require(
            q.shape == (7,) and np.isfinite(q).all() and np.linalg.norm(q[3:]) > 1e-6,
            "base_to_camera",
            "7 numbers x y z qx qy qz qw with a non-zero quaternion",
            self.base_to_camera,
        )
        require(
            not self.odom_from_tf or bool(self.odom_frame), "odom_frame", "a frame with odom_from_tf", self.odom_frame
        )
        require(self.gravity in GRAVITY_SOURCES, "gravity", f"one of {', '.join(GRAVITY_SOURCES)}", self.gravity)
        g = np.asarray(self.gravity_vector, dtype=np.float64)
        require(
            g.shape == (3,) and np.isfinite(g).all() and np.linalg.norm(g) > 1e-6,
            "gravity_vector",
            "3 numbers, not all zero",
            self.gravity_vector,
        )

    @property
    def T_base_cam(self) -> np.ndarray:
        """The camera's pose in ``base_frame`` (4x4, quaternion normalised)."""
        q = np.asarray(self.base_to_camera, dtype=np.float64)
        return pose_from_tum(np.concatenate([q[:3], q[3:] / np.linalg.norm(q[3:])]))


def map_alignment(
    opt: FrameOptions, T_world_cam0: np.ndarray, first: RgbdFrame, warn: Callable[[str], None]
) -> np.ndarray:
    """``T_map_world`` (4x4) from the first frame ``first`` at ``T_world_cam0`` (the module docstring);
    ``warn`` receives a line when the floor was asked for and not found."""
    T_cam_base = invert(opt.T_base_cam)
    T_world_base0 = T_world_cam0 @ T_cam_base
    down_cam = T_cam_base[:3, :3] @ np.array([0.0, 0.0, -1.0])  # the base's down, in the camera frame
    if opt.gravity == "vector":
        down_cam = np.asarray(opt.gravity_vector, dtype=np.float64)
    elif opt.gravity == "floor":
        found = floor_down(first.depth_m, first.intrinsics, -down_cam)
        if found is None:
            warn("gravity floor: no floor in the first depth image; map z is base_frame's z (extrinsic)")
        else:
            down_cam = found
    down_world = T_world_cam0[:3, :3] @ down_cam
    return level_frame(down_world, T_world_base0[:3, 0], T_world_base0[:3, 3])


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, w: float) -> np.ndarray:
    """The pose ``w`` of the way from ``T0`` to ``T1`` (0: ``T0``, 1: ``T1``): translation linear,
    rotation along the shortest arc."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))([w]).as_matrix()[0]
    out[:3, 3] = (1.0 - w) * T0[:3, 3] + w * T1[:3, 3]
    return out


class OdometryBuffer:
    """The ``parent -> child`` transforms that arrive on ``/tf`` (another node's odometry), by stamp: the
    newest ``capacity``. :meth:`at` interpolates between the two around a stamp, at most ``max_gap_s``
    apart, or takes the nearest within ``tolerance_s``."""

    def __init__(
        self, parent: str, child: str, capacity: int = 2000, max_gap_s: float = 0.5, tolerance_s: float = 0.05
    ):
        self.parent, self.child = parent, child
        self.capacity = capacity
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.tolerance_ns = int(tolerance_s * 1e9)
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._lock = threading.Lock()

    def add(self, msg: TFMessage) -> None:
        for t in msg.transforms:
            if t.header.frame_id != self.parent or t.child_frame_id != self.child:
                continue
            T = conversions.transform_from_msg(t)
            stamp = conversions.stamp_ns(t)
            with self._lock:
                i = bisect.bisect_left(self._stamps, stamp)
                if i < len(self._stamps) and self._stamps[i] == stamp:
                    self._poses[i] = T
                    continue
                self._stamps.insert(i, stamp)
                self._poses.insert(i, T)
                if len(self._stamps) > self.capacity:
                    del self._stamps[0], self._poses[0]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp_ns)
            if i < len(self._stamps) and self._stamps[i] == stamp_ns:
                return self._poses[i]
            if 0 < i < len(self._stamps):
                s0, s1 = self._stamps[i - 1], self._stamps[i]
                if s1 - s0 <= self.max_gap_ns:
                    return interpolate_pose(self._poses[i - 1], self._poses[i], (stamp_ns - s0) / (s1 - s0))
            near = [j for j in (i - 1, i) if 0 <= j < len(self._stamps)]
            if near:
                j = min(near, key=lambda j: abs(self._stamps[j] - stamp_ns))
                if abs(self._stamps[j] - stamp_ns) <= self.tolerance_ns:
                    return self._poses[j]
        return None


class TfOutput:
    """``/tf`` per frame and ``/tf_static`` once, for ``node`` (see the module docstring).

    :meth:`frame` takes each processed frame's camera pose in ``map`` and the previous frame's pose as it
    stands now (corrections applied), whose difference is the motion added to ``odom -> base``.
    """

    def __init__(self, node, opt: FrameOptions):
        self.opt = opt
        self.T_base_cam = opt.T_base_cam
        self._T_cam_base = invert(self.T_base_cam)
        # the QoS of tf2's broadcasters: /tf reliable, volatile, depth 100; /tf_static transient local
        self.pub = node.create_publisher(TFMessage, "/tf", qos.events(100)) if opt.publish_tf else None
        self.pub_static = node.create_publisher(TFMessage, "/tf_static", qos.state()) if opt.publish_tf else None
        self.T_odom_base: np.ndarray | None = None
        #: the camera's frame: ``camera_frame``, else the first image's frame id (odometry's child frame)
        self.camera_frame = opt.camera_frame or "camera"
        self.odometry: OdometryBuffer | None = None
        self._logger = node.get_logger()
        if opt.publish_tf and opt.odom_from_tf:
            self.odometry = OdometryBuffer(opt.odom_frame, opt.base_frame)
            node.create_subscription(TFMessage, "/tf", self.odometry.add, qos.events(100))

    def frame(self, T_map_cam: np.ndarray, T_map_cam_prev: np.ndarray | None, stamp_ns: int, camera_frame: str) -> None:
        """Publish the transforms of a frame at ``T_map_cam`` (``T_map_cam_prev``: the previous frame now,
        None for the first); ``camera_frame``: the image's frame id (used without ``camera_frame``)."""
        T_map_base = T_map_cam @ self._T_cam_base
        first = self.T_odom_base is None or T_map_cam_prev is None
        if first:
            self.camera_frame = self.opt.camera_frame or camera_frame or "camera"
            self.T_odom_base = T_map_base
        else:
            self.T_odom_base = self.T_odom_base @ invert(T_map_cam_prev @ self._T_cam_base) @ T_map_base
        if self.pub is None:
            return
        if first:
            msg = conversions.transform_msg(self.T_base_cam, stamp_ns, self.opt.base_frame, self.camera_frame)
            self.pub_static.publish(TFMessage(transforms=[msg]))
        o = self.opt
        if self.odometry is not None:
            T_odom_base = self.odometry.at(stamp_ns)
            if T_odom_base is None:
                self._logger.warning(
                    f"odom_from_tf: no {o.odom_frame} -> {o.base_frame} on /tf near frame {stamp_ns}: "
                    f"{o.map_frame} -> {o.odom_frame} not published for it",
                    throttle_duration_sec=5.0,
                )
                return
            msg = conversions.transform_msg(T_map_base @ invert(T_odom_base), stamp_ns, o.map_frame, o.odom_frame)
            self.pub.publish(TFMessage(transforms=[msg]))
            return
        if o.odom_frame:
            T_map_odom = T_map_base @ invert(self.T_odom_base)
            transforms = [
                conversions.transform_msg(T_map_odom, stamp_ns, o.map_frame, o.odom_frame),
                conversions.transform_msg(self.T_odom_base, stamp_ns, o.odom_frame, o.base_frame),
            ]
        else:
            transforms = [conversions.transform_msg(T_map_base, stamp_ns, o.map_frame, o.base_frame)]
        self.pub.publish(TFMessage(transforms=transforms))
