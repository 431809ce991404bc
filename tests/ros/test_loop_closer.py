"""The ``loop_closer`` node over real DDS: fed the keyframes of the synthetic loop with a drifted end, it
answers every keyframe on ``loop_closure`` and, at the end of the loop, publishes the corrected poses
that put the drifted end back on the ground truth."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "core" / "loop"))  # the synthetic loop of the core tests

from loop_scene import FRAME_NS, LOOP_FRAMES, pose_error, render_loop_views  # noqa: E402


def test_the_loop_closer_answers_every_keyframe_and_corrects_the_drifted_end(ros_env):
    rclpy = pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String

    from neb_slam_core.geometry.se3 import make_pose
    from neb_slam_ros import conversions, qos
    from neb_slam_ros.keyframe_link import KeyframeMeta

    views, intr = render_loop_views()
    drift = make_pose(Rotation.from_euler("y", 4.0, degrees=True).as_matrix(), [0.20, 0.0, -0.15])
    gt = {f: views[f][1] for f in LOOP_FRAMES}
    poses = [drift @ gt[f] if f >= 270 else gt[f] for f in LOOP_FRAMES]

    node_proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "neb_slam_ros.loop_closer",
            "--ros-args",
            "-p",
            "config:=ci",
            "-p",
            "loop.temporal_window:=2",
            "-p",
            "loop.neighbours:=1",
        ],
        env=ros_env,
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        os.environ[key] = ros_env[key]
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("loop_test", namespace="neb_slam", context=context)
    verdicts: list = []
    try:
        kinds = {"rgb": Image, "depth": Image, "camera_info": CameraInfo, "pose": PoseStamped, "meta": String}
        pubs = {part: node.create_publisher(kind, f"keyframe/{part}", qos.keyframes()) for part, kind in kinds.items()}
        node.create_subscription(PathMsg, "loop_closure", verdicts.append, qos.events(10))
        deadline = time.monotonic() + 60
        while min(p.get_subscription_count() for p in pubs.values()) == 0 or node.count_publishers("loop_closure") == 0:
            assert time.monotonic() < deadline, "the loop closer did not connect"
            time.sleep(0.1)
        for kid, (f, T) in enumerate(zip(LOOP_FRAMES, poses)):
            ns = f * FRAME_NS
            view = views[f][0]
            pubs["rgb"].publish(conversions.rgb_msg(view.rgb, ns, "camera"))
            pubs["depth"].publish(conversions.depth_msg(view.depth_m, ns, "camera"))
            pubs["camera_info"].publish(conversions.camera_info_msg(intr, None, ns, "camera"))
            pubs["pose"].publish(conversions.pose_msg(T, ns, "map"))
            pubs["meta"].publish(String(data=KeyframeMeta(ns, f, kid, False, kid == 0, T, np.zeros((0, 3))).to_json()))
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 120
        while len(verdicts) < len(LOOP_FRAMES) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.2)
        assert node_proc.poll() is None, "the loop closer died"
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        if node_proc.poll() is None:
            node_proc.send_signal(signal.SIGINT)
        out, _ = node_proc.communicate(timeout=60)
    assert node_proc.returncode == 0, out
    assert "Traceback" not in out, out
    # one verdict per keyframe, stamped with it, in order
    assert [conversions.stamp_ns(m) for m in verdicts] == [f * FRAME_NS for f in LOOP_FRAMES], out
    assert all(len(m.poses) == 0 for m in verdicts[:-1]), out
    last = verdicts[-1]
    assert len(last.poses) >= 1, out
    stamps = [conversions.stamp_ns(p) for p in last.poses]
    assert stamps[-1] == LOOP_FRAMES[-1] * FRAME_NS and stamps == sorted(stamps)
    err_m, err_deg = pose_error(conversions.pose_from_msg(last.poses[-1], "loop_closure"), gt[LOOP_FRAMES[-1]])
    assert err_m < 0.015 and err_deg < 0.3, (err_m, err_deg)
    assert "1 applied" in out
