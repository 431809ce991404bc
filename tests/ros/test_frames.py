"""Frames and TF (:mod:`neb_slam_ros.frames`) without DDS: the map's alignment from each gravity source, and
the transforms a sequence of poses with a correction in the middle puts on /tf."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]

frames = pytest.importorskip("neb_slam_ros.frames")

from neb_slam_core.geometry.se3 import invert, make_pose, pose_to_tum  # noqa: E402
from neb_slam_core.types import Intrinsics, RgbdFrame  # noqa: E402
from neb_slam_ros import conversions  # noqa: E402
from neb_slam_ros.params import ParameterError  # noqa: E402


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _wall_frame() -> RgbdFrame:
    """A camera 1 m in front of a wall: no floor in view."""
    K = Intrinsics(fx=50.0, fy=50.0, cx=15.5, cy=11.5, width=32, height=24)
    return RgbdFrame(np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32), K, 0)


T_WORLD_CAM0 = make_pose(_rot("y", 30.0) @ _rot("x", -12.0), np.array([0.4, -1.0, 2.0]))


def _tf(msg) -> np.ndarray:
    return conversions.transform_from_msg(msg)


@pytest.mark.parametrize(
    "changes, name",
    [
        ({"base_to_camera": (0.0, 0.0, 0.0)}, "base_to_camera"),
        ({"base_to_camera": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)}, "base_to_camera"),
        ({"gravity": "imu"}, "gravity"),
        ({"gravity_vector": (0.0, 0.0, 0.0)}, "gravity_vector"),
        ({"odom_frame": "map"}, "map_frame"),
        ({"base_frame": ""}, "base_frame"),
    ],
)
def test_a_bad_frame_option_names_itself(changes, name):
    import dataclasses

    opt = dataclasses.replace(frames.FrameOptions(), **changes)
    with pytest.raises(ParameterError, match=f"parameter {name}:"):
        opt.check()


def test_extrinsic_gravity_makes_the_first_base_pose_the_map():
    # a camera 0.3 m above the base origin, pitched 20 degrees down: map = the base at the first frame
    R_base_cam = frames.FrameOptions().T_base_cam[:3, :3] @ _rot("x", -20.0)
    q = pose_to_tum(make_pose(R_base_cam, np.array([0.1, 0.0, 0.3])))
    opt = frames.FrameOptions(base_to_camera=tuple(float(v) for v in q))
    opt.check()
    T_map_world = frames.map_alignment(opt, T_WORLD_CAM0, _wall_frame(), pytest.fail)
    np.testing.assert_allclose(T_map_world @ T_WORLD_CAM0 @ invert(opt.T_base_cam), np.eye(4), atol=1e-12)


def test_a_gravity_vector_sets_the_maps_up_and_the_base_keeps_its_heading():
    down_cam = _rot("x", -12.0).T @ np.array([0.0, 1.0, 0.2])  # any direction, in the first camera's frame
    down_cam /= np.linalg.norm(down_cam)
    opt = frames.FrameOptions(gravity="vector", gravity_vector=tuple(down_cam))
    T_map_world = frames.map_alignment(opt, T_WORLD_CAM0, _wall_frame(), pytest.fail)
    T_map_cam0 = T_map_world @ T_WORLD_CAM0
    np.testing.assert_allclose(T_map_cam0[:3, :3] @ down_cam, [0.0, 0.0, -1.0], atol=1e-12)
    # the base's origin is the map's, its forward axis lies in the map's x-z plane
    T_map_base0 = T_map_cam0 @ invert(opt.T_base_cam)
    np.testing.assert_allclose(T_map_base0[:3, 3], 0.0, atol=1e-12)
    assert abs(T_map_base0[1, 0]) < 1e-12 and T_map_base0[0, 0] > 0


def test_floor_gravity_without_a_floor_falls_back_to_the_extrinsic_with_a_warning():
    said: list[str] = []
    opt = frames.FrameOptions(gravity="floor")
    T = frames.map_alignment(opt, T_WORLD_CAM0, _wall_frame(), said.append)
    T_ext = frames.map_alignment(frames.FrameOptions(), T_WORLD_CAM0, _wall_frame(), pytest.fail)
    np.testing.assert_allclose(T, T_ext, atol=1e-12)
    assert len(said) == 1 and "no floor" in said[0]


class _Node:
    """Stands in for a node: its publishers record what they publish, its subscriptions are kept by topic,
    its logger keeps its warnings."""

    def __init__(self):
        self.sent: dict[str, list] = {}
        self.subscriptions: dict[str, object] = {}
        self.warnings: list[str] = []

    def get_logger(self):
        node = self

        class Logger:
            def warning(self, text, **kwargs):
                node.warnings.append(text)

        return Logger()

    def create_subscription(self, msg_type, topic, callback, qos):
        self.subscriptions[topic] = callback

    def create_publisher(self, msg_type, topic, qos):
        node = self

        class Pub:
            def publish(self, msg):
                node.sent.setdefault(topic, []).append(msg)

        return Pub()


def test_odom_to_base_is_continuous_and_map_to_odom_takes_a_correction():
    opt = frames.FrameOptions()
    node = _Node()
    tf = frames.TfOutput(node, opt)
    P0 = make_pose(_rot("z", 5.0), np.array([0.0, 0.0, 0.0]))
    M = make_pose(_rot("y", 3.0), np.array([0.02, -0.01, 0.05]))  # the camera's motion per frame
    C = make_pose(_rot("z", 2.0), np.array([0.1, 0.05, 0.0]))  # a correction between frames 1 and 2
    P1 = P0 @ M
    P2 = C @ P1 @ M  # tracked against the corrected map
    tf.frame(P0, None, 10, "cam_optical")
    tf.frame(P1, P0, 20, "cam_optical")
    tf.frame(P2, C @ P1, 30, "cam_optical")

    (static,) = node.sent["/tf_static"]
    (s,) = static.transforms
    assert (s.header.frame_id, s.child_frame_id) == ("base_link", "cam_optical")
    np.testing.assert_allclose(_tf(s), opt.T_base_cam, atol=1e-12)
    T_cb = invert(opt.T_base_cam)
    for msg, P, stamp in zip(node.sent["/tf"], (P0, P1, P2), (10, 20, 30)):
        map_odom, odom_base = msg.transforms
        assert (map_odom.header.frame_id, map_odom.child_frame_id) == ("map", "odom")
        assert (odom_base.header.frame_id, odom_base.child_frame_id) == ("odom", "base_link")
        assert map_odom.header.stamp.nanosec == odom_base.header.stamp.nanosec == stamp
        np.testing.assert_allclose(_tf(map_odom) @ _tf(odom_base) @ opt.T_base_cam, P, atol=1e-9)
    # odom -> base moved by the base's motion alone; the correction went to map -> odom
    odom = [_tf(m.transforms[1]) for m in node.sent["/tf"]]
    base_motion = invert(P0 @ T_cb) @ (P1 @ T_cb)
    np.testing.assert_allclose(odom[2], odom[1] @ base_motion, atol=1e-9)
    np.testing.assert_allclose(_tf(node.sent["/tf"][1].transforms[0]), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(_tf(node.sent["/tf"][2].transforms[0]), C, atol=1e-9)


def test_without_an_odom_frame_map_to_base_goes_out_and_the_camera_frame_parameter_wins():
    opt = frames.FrameOptions(odom_frame="", camera_frame="rig/depth_optical", publish_tf=True)
    node = _Node()
    tf = frames.TfOutput(node, opt)
    P0 = make_pose(_rot("x", 10.0), np.array([1.0, 2.0, 0.5]))
    tf.frame(P0, None, 7, "from_the_header")
    (m,) = node.sent["/tf"][0].transforms
    assert (m.header.frame_id, m.child_frame_id) == ("map", "base_link")
    np.testing.assert_allclose(_tf(m) @ opt.T_base_cam, P0, atol=1e-9)
    assert node.sent["/tf_static"][0].transforms[0].child_frame_id == "rig/depth_optical"
    quiet = _Node()
    frames.TfOutput(quiet, frames.FrameOptions(publish_tf=False)).frame(P0, None, 7, "x")
    assert quiet.sent == {}


def test_with_the_robots_own_odometry_only_map_to_odom_goes_out_and_absorbs_its_drift():
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    from neb_slam_ros.conversions import header

    opt = frames.FrameOptions(odom_from_tf=True)
    node = _Node()
    tf = frames.TfOutput(node, opt)

    def base(t: float) -> np.ndarray:  # the base in map: turning about z and moving, uniformly in t
        return make_pose(_rot("z", 2.0 * t), np.array([0.1 * t, 0.02 * t, 0.0]))

    ns = 10_000_000  # t = 1: 10 ms
    D = make_pose(_rot("z", 7.0), np.array([0.3, -0.1, 0.0]))  # the robot's odometry drifted by D
    for t in (5, 15, 25):  # its odom -> base, stamped between the frames
        T = invert(D) @ base(t)
        msg = conversions.transform_msg(T, t * ns, "odom", "base_link")
        other = TransformStamped(header=header(t * ns, "map"), child_frame_id="odom")  # ours: ignored
        node.subscriptions["/tf"](TFMessage(transforms=[msg, other]))
    T_base_cam = opt.T_base_cam
    tf.frame(base(10) @ T_base_cam, None, 10 * ns, "cam")
    tf.frame(base(20) @ T_base_cam, base(10) @ T_base_cam, 20 * ns, "cam")
    for msg in node.sent["/tf"]:
        (m,) = msg.transforms
        assert (m.header.frame_id, m.child_frame_id) == ("map", "odom")
        np.testing.assert_allclose(_tf(m), D, atol=1e-9)  # interpolated odometry at 10 and 20
    assert len(node.sent["/tf"]) == 2 and node.warnings == []
    tf.frame(base(100) @ T_base_cam, base(20) @ T_base_cam, 100 * ns, "cam")  # 0.75 s from odometry: nothing
    assert len(node.sent["/tf"]) == 2 and f"no odom -> base_link on /tf near frame {100 * ns}" in node.warnings[0]


def test_odom_from_tf_needs_an_odom_frame():
    with pytest.raises(ParameterError, match="parameter odom_frame:"):
        frames.FrameOptions(odom_from_tf=True, odom_frame="").check()
