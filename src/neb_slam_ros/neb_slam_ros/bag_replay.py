"""``bag_replay``: plays a converted RGB-D bag into the suite, with ``/clock``.

Reads a ROS 2 bag (sqlite3 or mcap; ROS 1 ``.bag`` files too) with the core's bag loader, which finds the
colour, depth, camera-info and ground-truth topics and pairs colour with depth by stamp, and publishes
each frame on ``rgb/image`` (rgb8), ``depth/image`` (32FC1 metres: exact), ``rgb/camera_info`` (with the
bag's distortion) and, when the bag has ground truth, ``ground_truth/pose``; stamps are the bag's.

``rate`` 1.0 plays at recorded speed (0: as fast as possible). ``lockstep`` publishes the next frame
only after the tracker published the pose of the previous one (``pose``): deterministic and lossless on
a slow machine. ``start``/``count`` select frames; at the end it stops the process, or starts over with
``loop``: every pass is stamped after the one before (the frame period later than its last frame), so
time runs forward as from a camera, and with ``loop_reverse`` every second pass plays the frames
backwards, so that the camera's motion stays continuous where the recording's end is far from its start
(long runs over one recording).

Example::

    ros2 run neb_slam_ros bag_replay --ros-args -p bag:=bags/fr1_xyz -p lockstep:=true
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image

from neb_slam_core.datasets.bag import BagDataset
from neb_slam_core.errors import DatasetError
from neb_slam_ros import conversions, qos
from neb_slam_ros._node_main import request_stop, run_node
from neb_slam_ros.node import NebNode
from neb_slam_ros.params import ParameterError, require


@dataclass(frozen=True)
class ReplayOptions:
    bag: str = ""
    rate: float = 1.0
    lockstep: bool = False
    lockstep_timeout_s: float = 300.0
    start: int = 0
    count: int = 0
    loop: bool = False
    loop_reverse: bool = False
    wait_for_subscribers_s: float = 60.0
    depth_scale: float = 0.001
    camera_frame_id: str = "camera"
    world_frame_id: str = "map"

    PARAMETER_DOCS = {
        "bag": "the bag: a ROS 2 bag folder (sqlite3 or mcap) or a ROS 1 .bag file",
        "rate": "playback speed, 1.0 = as recorded, 0 = as fast as possible",
        "lockstep": "publish the next frame only after the tracker published the previous frame's pose",
        "lockstep_timeout_s": "in lockstep, go on (with a warning) when no pose came within this",
        "start": "first frame to play (0-based)",
        "count": "frames to play (0: all)",
        "loop": "start over at the end instead of stopping (each pass stamped after the one before)",
        "loop_reverse": "with loop: play every second pass backwards (continuous motion across passes)",
        "wait_for_subscribers_s": "wait this long for the tracker's subscriptions (and, in lockstep, its pose "
        "publisher) before the first frame",
        "depth_scale": "metres per unit of the bag's 16UC1 depth",
        "camera_frame_id": "frame_id of the published images",
        "world_frame_id": "frame_id of the published ground-truth poses",
    }

    def check(self) -> None:
        require(bool(self.bag), "bag", "the path of a bag (-p bag:=bags/NAME)", self.bag)
        require(self.rate >= 0, "rate", ">= 0", self.rate)
        require(self.lockstep_timeout_s > 0, "lockstep_timeout_s", "> 0", self.lockstep_timeout_s)
        require(self.wait_for_subscribers_s >= 0, "wait_for_subscribers_s", ">= 0", self.wait_for_subscribers_s)
        require(self.start >= 0, "start", ">= 0", self.start)
        require(self.count >= 0, "count", ">= 0 (0: all)", self.count)
        require(self.depth_scale > 0, "depth_scale", "> 0", self.depth_scale)


class BagReplayNode(NebNode):
    """Publishes a bag's frames; see the module docstring."""

    def __init__(self) -> None:
        super().__init__("bag_replay", ReplayOptions, with_config=False, join_timeout_s=10.0)
        try:
            self.dataset = BagDataset(self.opt.bag, depth_scale=self.opt.depth_scale)
        except DatasetError as exc:
            raise ParameterError("bag", str(exc)) from None
        n = len(self.dataset)
        stop = n if self.opt.count == 0 else min(n, self.opt.start + self.opt.count)
        self.indices = range(min(self.opt.start, n), stop)
        reliable = qos.camera(True)
        self.pub_rgb = self.create_publisher(Image, "rgb/image", reliable)
        self.pub_depth = self.create_publisher(Image, "depth/image", reliable)
        self.pub_info = self.create_publisher(CameraInfo, "rgb/camera_info", reliable)
        self.pub_gt = self.create_publisher(PoseStamped, "ground_truth/pose", qos.events())
        self.pub_clock = self.create_publisher(Clock, "/clock", 10)
        self._last_pose_ns = -1
        self.n_published = 0
        self._passes = 0
        self._last_stamp_ns = 0  # the last stamp of the previous pass
        if self.opt.lockstep:
            self.create_subscription(PoseStamped, "pose", self._on_pose, qos.stream())
        self.start_worker()
        self.get_logger().info(
            f"neb_slam bag_replay started: {self.opt.bag}, frames {self.indices.start}.."
            f"{self.indices.stop - 1} of {n}, rate {self.opt.rate:g}, lockstep {self.opt.lockstep}"
        )

    def _on_pose(self, msg: PoseStamped) -> None:
        with self.cond:
            self._last_pose_ns = max(self._last_pose_ns, conversions.stamp_ns(msg))
            self.cond.notify_all()

    def _wait_for_pose(self, stamp_ns: int) -> None:
        deadline = time.monotonic() + self.opt.lockstep_timeout_s
        with self.cond:
            while self._last_pose_ns < stamp_ns and not self.stopping:
                left = deadline - time.monotonic()
                if left <= 0:
                    self.get_logger().warning(
                        f"lockstep: no pose for frame {stamp_ns} within "
                        f"{self.opt.lockstep_timeout_s:g} s (skipped by the tracker?): going on"
                    )
                    return
                self.cond.wait(min(left, 0.5))

    def _wait_for_subscribers(self) -> None:
        """Frames published before the tracker subscribed would be lost: wait for it (discovery takes a
        moment), up to ``wait_for_subscribers_s``."""
        deadline = time.monotonic() + self.opt.wait_for_subscribers_s
        pubs = (self.pub_rgb, self.pub_depth, self.pub_info)
        while not self.stopping and time.monotonic() < deadline:
            if all(p.get_subscription_count() > 0 for p in pubs) and (
                not self.opt.lockstep or self.count_publishers(self.resolve_topic_name("pose")) > 0
            ):
                return
            self.wait_stopping(0.1)
        if not self.stopping:
            self.get_logger().warning(
                f"no tracker subscribed after {self.opt.wait_for_subscribers_s:g} s: publishing anyway"
            )

    def work_loop(self) -> None:
        """The replay (the worker thread): the bag's frames at ``rate``, then the process ends."""
        try:
            self._wait_for_subscribers()
            self.get_logger().info(f"publishing frames ({len(self.indices)})")
            while not self.stopping:
                self._play_once()
                if not self.opt.loop:
                    break
            if not self.stopping:
                # the last frames must reach their subscribers before the process ends (reliable QoS: they
                # acknowledge them)
                for pub in (self.pub_info, self.pub_depth, self.pub_rgb):
                    pub.wait_for_all_acked(Duration(seconds=5.0))
                self.get_logger().info(f"neb_slam bag_replay finished: {self.n_published} frames published")
                request_stop()  # ends the process's spin: the replay is over
        except Exception as exc:  # report, and end the process rather than hang
            self.get_logger().error(f"bag_replay failed: {type(exc).__name__}: {exc}")
            request_stop()

    def _pass_stamps(self) -> tuple[range, list[int]]:
        """This pass's frame indices and their published stamps: the bag's, shifted to follow the previous
        pass; a reversed pass mirrors the stamps, so the gaps between frames stay the recording's."""
        reverse = self.opt.loop_reverse and self._passes % 2 == 1
        indices = self.indices[::-1] if reverse else self.indices
        raw = [int(self.dataset.stamps_ns[i]) for i in self.indices]
        if reverse:
            raw = [raw[0] + raw[-1] - ns for ns in reversed(raw)]
        if self._passes == 0:
            self._offset_ns = 0
        else:
            period = (raw[-1] - raw[0]) // max(1, len(raw) - 1)
            self._offset_ns = self._last_stamp_ns + period - raw[0]
        self._passes += 1
        stamps = [ns + self._offset_ns for ns in raw]
        self._last_stamp_ns = stamps[-1]
        return indices, stamps

    def _play_once(self) -> None:
        t0, stamp0 = time.monotonic(), None
        camera, world = self.opt.camera_frame_id, self.opt.world_frame_id
        indices, stamps = self._pass_stamps()
        for i, ns in zip(indices, stamps):
            if self.stopping:
                return
            frame = self.dataset[i]
            stamp0 = ns if stamp0 is None else stamp0
            if self.opt.rate > 0:
                delay = t0 + (ns - stamp0) * 1e-9 / self.opt.rate - time.monotonic()
                if delay > 0:
                    self.wait_stopping(delay)
            self.pub_clock.publish(Clock(clock=conversions.to_time(ns)))
            if frame.T_world_cam is not None:
                self.pub_gt.publish(conversions.pose_msg(frame.T_world_cam, ns, world))
            self.pub_info.publish(
                conversions.camera_info_msg(frame.intrinsics, frame.extras.get("distortion"), ns, camera)
            )
            self.pub_depth.publish(conversions.depth_msg(frame.depth_m, ns, camera))
            self.pub_rgb.publish(conversions.rgb_msg(frame.rgb, ns, camera))
            self.n_published += 1
            if self.opt.lockstep:
                self._wait_for_pose(ns)

    def finish(self) -> None:
        self.dataset.close()


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``bag_replay`` executable; returns the exit status."""
    return run_node(BagReplayNode, args)


if __name__ == "__main__":
    sys.exit(main())
