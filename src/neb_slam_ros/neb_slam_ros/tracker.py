"""``tracker``: per-frame camera pose, keyframes and neural-block allocation.

Subscribes ``rgb/image``, ``depth/image`` and ``rgb/camera_info`` (colour and depth paired by stamp), tracks
each frame against its copy of the map (the engine's :class:`~neb_slam_core.slam.Frontend`) and publishes
``pose``, ``odometry``, ``path``, the keyframes (``keyframe/*``) and the blocks (``blocks``). The map comes
from the mapper's ``map_update`` messages. Before frame 2 it waits for the mapper's first update; with
``map_sync`` (default) that is the whole first map, and it also waits, after each keyframe that triggers
mapping, for the update that integrates it, so it computes exactly what the one-process engine computes;
without, it waits for the first ``live.first_iterations`` steps of the first map only, and tracks the
newest frame while the mapper works; with ``loop_sync`` it waits,
after each keyframe, for the loop closer's verdict on it as well. With ``wait_for_map`` it waits for a
map before its first frame (a mapper continuing a checkpoint, ``map_file``) and tracks that frame
against it, from its first pose (``ground_truth_topic`` or the identity), instead of starting a new
map. Frames that arrive meanwhile
are queued (``frame_queue`` of them; older ones are dropped with a counted warning; lockstep replay never
queues more than one).

A mapper that restarts from its checkpoint (``checkpoint_every``) announces itself with a new ``epoch`` on
``map_update`` and the keyframes it kept: the tracker takes its map and sends the keyframes after those
again, from the ones it keeps until a mapper checkpoint holds them (at most ``resend_keyframes``); it
goes on without a restart of its own.

Example::

    ros2 run neb_slam_ros tracker --ros-args -p config:=tum
    python -m neb_slam_ros.tracker --ros-args -r __ns:=/robot1/neb_slam --params-file my.yaml
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String, UInt8MultiArray

from neb_slam_core.scene import map_update
from neb_slam_core.slam import Frontend, FrontendStep, new_block_map
from neb_slam_core.types import RgbdFrame
from neb_slam_ros import conversions, qos
from neb_slam_ros._node_main import run_node
from neb_slam_ros.camera_input import CameraInput, InputOptions
from neb_slam_ros.frames import WORLD_FRAME, FrameOptions, map_alignment
from neb_slam_ros.keyframe_link import KeyframeMeta
from neb_slam_ros.node import NebNode
from neb_slam_ros.outputs import CAMERA_FRAME, HealthOutput, PoseOutputs, block_centres
from neb_slam_ros.params import declare_options, require


@dataclass(frozen=True)
class TrackerOptions:
    """The tracker's own parameters (the camera input's are :class:`InputOptions`, the engine's the config)."""

    map_sync: bool = True
    loop_sync: bool = False
    wait_for_map: bool = False
    map_timeout_s: float = 600.0
    initial_pose_timeout_s: float = 10.0
    path_period_s: float = 1.0
    resend_keyframes: int = 40

    PARAMETER_DOCS = {
        "map_sync": "after a keyframe that triggers mapping, wait for its map update before the next frame",
        "loop_sync": "after each keyframe, wait for the loop closer's verdict on it (needs a loop_closer running)",
        "wait_for_map": "before the first frame, wait for the map of a mapper that continues a map_file",
        "map_timeout_s": "warn when an awaited map update or loop verdict takes longer than this",
        "initial_pose_timeout_s": "how long the first frame waits for its pose on ground_truth_topic",
        "path_period_s": "publish the path at most this often, and at once after a loop correction (0: after "
        "every frame)",
        "resend_keyframes": "keyframes kept for a mapper that restarts from its checkpoint, at most (the ones "
        "its last checkpoint holds are let go; 0: none)",
    }

    def check(self) -> None:
        require(self.map_timeout_s > 0, "map_timeout_s", "> 0", self.map_timeout_s)
        require(self.initial_pose_timeout_s >= 0, "initial_pose_timeout_s", ">= 0", self.initial_pose_timeout_s)
        require(self.path_period_s >= 0, "path_period_s", ">= 0", self.path_period_s)
        require(self.resend_keyframes >= 0, "resend_keyframes", ">= 0", self.resend_keyframes)


class TrackerNode(NebNode):
    """Tracks every frame against the latest map it has; see the module docstring."""

    def __init__(self) -> None:
        super().__init__("tracker", TrackerOptions, join_timeout_s=60.0)
        self.input_opt = declare_options(self, InputOptions)
        self.frame_opt = declare_options(self, FrameOptions)
        torch.manual_seed(self.cfg.seed)
        self.block_map = new_block_map(self.cfg)
        self.frontend: Frontend | None = None  # made at the first frame (its pose may come from a topic)
        self._updates: deque = deque()
        self._awaited_ack: int | None = None  # stamp of the keyframe whose map update we wait for
        self._acked = -1
        self._awaited_loop: int | None = None  # stamp of the keyframe whose loop verdict we wait for
        self._loop_checked = -1
        self._map_version = 0
        self._mapper_epoch: int | None = None  # the start of the mapper whose updates come
        # keyframes sent that the mapper's last checkpoint does not hold: a restarted mapper gets them again
        self._unsaved: deque[tuple[KeyframeMeta, RgbdFrame]] = deque()
        self._loop_stamp = -1  # the newest loop correction the map updates have carried
        self._waited_since: float | None = None
        self._keyframe_stamps: list[int] = []
        self._lag_max = 0

        self.input = CameraInput(self, self.input_opt, self.cond, thin=not self.opt.map_sync)
        self.create_subscription(UInt8MultiArray, "map_update", self._on_map_update, qos.events(10))
        if self.opt.loop_sync:
            self.create_subscription(Path, "loop_closure", self._on_loop_verdict, qos.events(10))
        self.poses = PoseOutputs(
            self,
            self.frame_opt,
            self.cfg.block.edge_m,
            lambda: self.frontend.trajectory(),
            lambda i: self.frontend.pose_of(i),
            self.opt.path_period_s,
        )
        self.health = HealthOutput(self, self.input, self._health_values)
        self.pub_kf = {
            "rgb": self.create_publisher(Image, "keyframe/rgb", qos.keyframes()),
            "depth": self.create_publisher(Image, "keyframe/depth", qos.keyframes()),
            "camera_info": self.create_publisher(CameraInfo, "keyframe/camera_info", qos.keyframes()),
            "pose": self.create_publisher(PoseStamped, "keyframe/pose", qos.keyframes()),
            "meta": self.create_publisher(String, "keyframe/meta", qos.keyframes()),
        }
        self.start_worker()
        self.get_logger().info(
            f"neb_slam tracker started (config {self.get_parameter('config').value}, "
            f"map_sync {self.opt.map_sync}, inputs {', '.join(self.input.topics)})"
        )

    # ------------------------------------------------------------------ callbacks (executor thread)

    def _on_map_update(self, msg: UInt8MultiArray) -> None:
        update = conversions.map_update_from_msg(msg, self)
        if update is None:
            return
        with self.cond:
            self._updates.append(update)
            self.cond.notify_all()

    def _on_loop_verdict(self, msg: Path) -> None:
        with self.cond:  # the corrected poses themselves come with the mapper's next map update
            self._loop_checked = max(self._loop_checked, conversions.stamp_ns(msg))
            self.cond.notify_all()

    # ------------------------------------------------------------------ worker thread

    def _waiting_for_map(self) -> bool:
        """A map update or a loop verdict the next frame has to wait for has not come yet."""
        return (
            (self.opt.wait_for_map and self._map_version == 0)
            or (self._awaited_ack is not None and self._acked < self._awaited_ack)
            or (self._awaited_loop is not None and self._loop_checked < self._awaited_loop)
        )

    def has_work(self) -> bool:
        return bool(self._updates) or (self.input.has_frame and not self._waiting_for_map())

    def take_work(self) -> tuple[list, RgbdFrame | None]:
        updates = list(self._updates)
        self._updates.clear()
        if self._waiting_for_map():
            return updates, None
        # in sync with the mapper every frame is tracked in order; otherwise the newest one (within
        # live.max_gap_s of the last processed frame)
        if self.opt.map_sync:
            return updates, self.input.pop()
        if self.frontend is None:
            return updates, self.input.pop_newest()
        return updates, self.input.pop_chosen(self.frontend.next_frame)

    def do_work(self, work: tuple[list, RgbdFrame | None]) -> None:
        updates, frame = work
        for u in updates:
            self._apply(u)
        self._warn_when_waiting_long()
        if frame is not None:
            try:
                self._track(frame)
            except Exception as exc:  # a frame must never kill the node
                self.get_logger().error(
                    f"frame {frame.stamp_ns} failed in the engine ({type(exc).__name__}: {exc}); skipped"
                )

    def _warn_when_waiting_long(self) -> None:
        if not self._waiting_for_map():
            self._waited_since = None
            return
        self._waited_since = self._waited_since or time.monotonic()
        if time.monotonic() - self._waited_since > self.opt.map_timeout_s:
            if self._map_version == 0 and self.opt.wait_for_map:
                what = "no map yet (wait_for_map): is a mapper with map_file running?"
            else:
                what = (
                    f"no map update or loop verdict for keyframe {self._awaited_ack}: are the mapper "
                    "and (with loop_sync) the loop closer running?"
                )
            self.get_logger().warning(f"{what} (waited {self.opt.map_timeout_s:.0f} s)")
            self._waited_since = time.monotonic()

    def _first_pose(self, stamp_ns: int) -> np.ndarray:
        topic = self.input_opt.ground_truth_topic
        if not topic:
            return np.eye(4)
        T = self.input.wait_for_ground_truth(stamp_ns, self.opt.initial_pose_timeout_s, lambda: self.stopping)
        if T is None:
            self.get_logger().warning(
                f"no pose on {topic} near the first frame's stamp after "
                f"{self.opt.initial_pose_timeout_s:g} s: starting from the identity"
            )
            return np.eye(4)
        return T

    def _apply(self, update: map_update.MapUpdate) -> None:
        restarted = self._mapper_epoch is not None and update.epoch not in (0, self._mapper_epoch)
        if self._mapper_epoch is None or restarted:
            self._mapper_epoch, self._map_version = update.epoch, 0  # its versions count from its start
        if update.version <= self._map_version:
            return  # a duplicate or a late one: newer state is already in
        try:
            map_update.apply(update, self.block_map)
        except map_update.MapUpdateError as exc:
            self.get_logger().error(f"map update {update.version} does not fit this tracker's map: {exc}")
            return
        self._map_version = update.version
        self._acked = update.ack_stamp_ns if restarted else max(self._acked, update.ack_stamp_ns)
        self._forget_saved(update.durable_keyframes)
        if restarted:
            self._resend(len(update.keyframe_poses))
        loop = update.loop_stamp_ns > self._loop_stamp  # a loop correction: the path goes out at once
        self._loop_stamp = max(self._loop_stamp, update.loop_stamp_ns)
        if self.frontend is not None and len(update.keyframe_poses):
            self.frontend.set_keyframe_poses(update.keyframe_poses)
            self.poses.path.changed(now=loop)

    def _track(self, frame: RgbdFrame) -> None:
        if self.frontend is None:
            self.frontend = Frontend(self.cfg, self.block_map, self._first_pose(frame.stamp_ns), own_map=True)
        step = self.frontend.step(frame)
        r = step.result
        if r.frame_index == 0:
            self.poses.align(map_alignment(self.frame_opt, r.T_world_cam, step.frame, self.get_logger().warning))
        self.poses.path.changed()
        if r.new_block_id is not None:
            self.poses.publish_blocks(block_centres(self.block_map), r.stamp_ns)
        if step.keyframe_id is not None:
            self._publish_keyframe(step)
            self._keyframe_stamps.append(r.stamp_ns)
        self._lag_max = max(self._lag_max, self.mapping_lag())
        with self.cond:
            if step.map_now and (self.opt.map_sync or step.first):
                self._awaited_ack = r.stamp_ns
            if step.keyframe_id is not None and self.opt.loop_sync:
                self._awaited_loop = r.stamp_ns
        self.poses.publish_frame(r, self.input.frame_id)
        self.health.frame(r)
        if not r.tracking_ok:
            self.get_logger().warning(
                f"frame {r.frame_index} ({r.stamp_ns}): tracking failed ({r.failure_reason}); "
                "kept the motion prediction"
            )

    def _first_iterations(self) -> int:
        """Map-only steps of the first map this tracker waits for: all of ``mapping.first_iterations`` in
        sync with the mapper (the one-process engine's order), ``live.first_iterations`` otherwise (the
        mapper fits the rest in the background while this tracker goes on)."""
        return self.cfg.mapping.first_iterations if self.opt.map_sync else self.cfg.live.first_iterations

    def _health_values(self) -> dict[str, object]:
        f = self.frontend
        return {
            "frames_processed": 0 if f is None else f.n_frames,
            "mapping_lag": self.mapping_lag(),
            "blocks": len(self.block_map),
            "keyframes": 0 if f is None else len(f.keyframe_poses),
            "map_version": self._map_version,
        }

    def _publish_keyframe(self, step: FrontendStep) -> None:
        r = step.result
        meta = KeyframeMeta(
            r.stamp_ns,
            r.frame_index,
            step.keyframe_id,
            step.map_now,
            step.first,
            r.T_world_cam,
            block_centres(self.block_map),
            self.poses.T_map_world,
            self._first_iterations() if step.first else None,
        )
        self._send_keyframe(meta, step.frame)
        if self.opt.resend_keyframes:
            self._unsaved.append((meta, step.frame))
            while len(self._unsaved) > self.opt.resend_keyframes:
                self._unsaved.popleft()

    def _forget_saved(self, durable_keyframes: int) -> None:
        """Let go of the keyframes the mapper's last checkpoint holds (all: it writes none, -1)."""
        while self._unsaved and (durable_keyframes < 0 or self._unsaved[0][0].keyframe_id < durable_keyframes):
            self._unsaved.popleft()

    def _resend(self, first_id: int) -> None:
        """Keyframes ``first_id`` on to a mapper that restarted with the keyframes before them."""
        n_sent = len(self.frontend.keyframe_poses) if self.frontend is not None else 0
        if first_id >= n_sent:
            self.get_logger().info(f"the mapper restarted with all {first_id} keyframes")
            return
        kept = [(meta, frame) for meta, frame in self._unsaved if meta.keyframe_id >= first_id]
        if not kept or kept[0][0].keyframe_id != first_id:
            self.get_logger().error(
                f"the mapper restarted with {first_id} of {n_sent} keyframes, and keyframes {first_id}.."
                f"{(kept[0][0].keyframe_id if kept else n_sent) - 1} are no longer kept (resend_keyframes "
                f"{self.opt.resend_keyframes}): its map misses them"
            )
        centres = block_centres(self.block_map)
        for meta, frame in kept:  # at the poses the keyframes have now, with every block allocated since
            T = self.frontend.keyframe_poses[meta.keyframe_id].copy()
            self._send_keyframe(dataclasses.replace(meta, T_world_cam=T, block_centres=centres), frame)
        self.get_logger().warning(f"the mapper restarted with {first_id} of {n_sent} keyframes: {len(kept)} sent again")

    def _send_keyframe(self, meta: KeyframeMeta, f: RgbdFrame) -> None:
        ns = meta.stamp_ns
        self.pub_kf["rgb"].publish(conversions.rgb_msg(f.rgb, ns, CAMERA_FRAME))
        self.pub_kf["depth"].publish(conversions.depth_msg(f.depth_m, ns, CAMERA_FRAME))
        self.pub_kf["camera_info"].publish(conversions.camera_info_msg(f.intrinsics, None, ns, CAMERA_FRAME))
        self.pub_kf["pose"].publish(conversions.pose_msg(meta.T_world_cam, ns, WORLD_FRAME))
        self.pub_kf["meta"].publish(String(data=meta.to_json()))

    # ------------------------------------------------------------------ shutdown

    def mapping_lag(self) -> int:
        """Keyframes sent to the mapper that no map update has acknowledged yet."""
        return sum(1 for s in self._keyframe_stamps if s > self._acked)

    def finish(self) -> None:
        with self.cond:
            self.input.drop_queued()  # arrived after the last frame the tracker took
        if self.frontend is not None:
            self.poses.path.flush()  # the frames of the last period
        n = 0 if self.frontend is None else self.frontend.n_frames
        self.final_log(
            f"neb_slam tracker stopped: {n} frames tracked ({self.health.failures} failed), "
            f"{len(self.block_map)} blocks, "
            f"{self.input.n_dropped} dropped, {self.input.warnings.total} input warnings; "
            f"{self.input.n_accepted} frames in, mapping lag {self.mapping_lag()} (max {self._lag_max})"
        )


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``tracker`` executable; returns the exit status."""
    return run_node(TrackerNode, args)


if __name__ == "__main__":
    sys.exit(main())
