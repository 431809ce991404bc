"""``loop_closer``: bag-of-words place recognition over keyframes and the loop's pose correction.

Subscribes the tracker's keyframes (``keyframe/*``) and keeps every one in the engine's
:class:`~neb_slam_core.loop.closer.LoopCloser` (ORB words in an inverted-index database, depth maps for
the correction). Keyframe poses are the tracker's, replaced by the mapper's refined ones as its
``map_update`` messages bring them (once an update says the mapper has handled the newest correction
published here: older ones still hold the poses from before it). For each new keyframe it runs the paper's loop
query; when a loop is
found, verified and its correction fitted, it publishes ``loop_closure`` (nav_msgs/Path): the corrected
poses of the keyframes from just after the loop's older end to the new keyframe, each pose stamped with
its keyframe's stamp. Every checked keyframe gets a ``loop_closure`` message stamped (header) with that
keyframe's stamp: with no poses when there is nothing to correct. A tracker with ``loop_sync`` waits
for it before the next frame, so that a replay does not end before its last keyframes were checked. The mapper
applies it (and re-optimises), and its next ``map_update`` carries the
corrected poses to the tracker, which republishes ``path`` whole.

Example::

    ros2 run neb_slam_ros loop_closer --ros-args -p config:=tum
    python -m neb_slam_ros.loop_closer --ros-args -r __ns:=/robot1/neb_slam -p loop.top_k:=5
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from nav_msgs.msg import Path
from std_msgs.msg import UInt8MultiArray

from neb_slam_core.loop.closer import LoopCloser
from neb_slam_ros import conversions, qos
from neb_slam_ros._node_main import run_node
from neb_slam_ros.frames import WORLD_FRAME
from neb_slam_ros.keyframe_link import KeyframeMeta, KeyframeSubscriber
from neb_slam_ros.node import NebNode
from neb_slam_ros.params import require


@dataclass(frozen=True)
class LoopCloserOptions:
    """The loop closer's own parameters (loop detection and correction come from the config's ``loop``)."""

    frame_id: str = WORLD_FRAME

    PARAMETER_DOCS = {"frame_id": "frame of the published corrected poses (the engine's world frame)"}

    def check(self) -> None:
        require(bool(self.frame_id), "frame_id", "a frame name", self.frame_id)


class LoopCloserNode(NebNode):
    """Detects loops among the keyframes and publishes their corrections; see the module docstring."""

    background = True

    def __init__(self) -> None:
        super().__init__("loop_closer", LoopCloserOptions, join_timeout_s=60.0)
        # loop.enabled false: the node runs (a launch file need not change) but checks nothing
        self.closer = LoopCloser(self.cfg.loop, seed=self.cfg.seed + 4) if self.cfg.loop.enabled else None
        self._poses: list[np.ndarray] = []  # keyframe id -> current pose
        self._stamps: list[int] = []  # keyframe id -> stamp
        self._mapper_poses: np.ndarray | None = None  # the newest map update's keyframe poses
        self._map_version = 0
        self._sent_loop_stamp = -1  # the newest correction published: older map updates do not carry it
        self.n_loops = 0
        self.n_detected = 0

        self._keyframes = KeyframeSubscriber(self, self.cond)
        self.create_subscription(UInt8MultiArray, "map_update", self._on_map_update, qos.events(10))
        self.pub_loop = self.create_publisher(Path, "loop_closure", qos.events(10))
        self.start_worker()
        what = (
            f"vocabulary {self.closer.detector.vocabulary.n_words} words"
            if self.closer is not None
            else "loop.enabled is false: no loop will be checked"
        )
        self.get_logger().info(f"neb_slam loop_closer started (config {self.get_parameter('config').value}, {what})")

    # ------------------------------------------------------------------ callbacks (executor thread)

    def _on_map_update(self, msg: UInt8MultiArray) -> None:
        update = conversions.map_update_from_msg(msg, self)
        if update is None:
            return
        with self.cond:
            # an update the mapper sent before it applied our newest correction holds the poses from
            # before it: taking them would undo the correction (and find the same loop again)
            if (
                update.version > self._map_version
                and len(update.keyframe_poses)
                and update.loop_stamp_ns >= self._sent_loop_stamp
            ):
                self._map_version = update.version
                self._mapper_poses = np.array(update.keyframe_poses, dtype=np.float64)

    # ------------------------------------------------------------------ worker thread

    def has_work(self) -> bool:
        return self._keyframes.assembler.has_ready

    def take_work(self) -> tuple[list[dict], np.ndarray | None]:
        refined, self._mapper_poses = self._mapper_poses, None
        return self._keyframes.assembler.pop_ready(), refined

    def do_work(self, work: tuple[list[dict], np.ndarray | None]) -> None:
        ready, refined = work
        if refined is not None:
            for k, T in enumerate(refined[: len(self._poses)]):
                self._poses[k] = T
        self._check_all(ready)

    def _check_all(self, ready: list[dict]) -> None:
        for parts in ready:
            try:
                self._check(parts)
            except Exception as exc:  # never let one keyframe kill the node
                self.get_logger().error(f"keyframe {parts['meta'].keyframe_id} failed: {type(exc).__name__}: {exc}")

    def _check(self, parts: dict) -> None:
        """Check one keyframe and publish the verdict (whatever happened: a loop_sync tracker waits for it)."""
        meta: KeyframeMeta = parts["meta"]
        verdict = None
        try:
            verdict = self._detect(meta, parts)
        finally:
            if verdict is None:
                verdict = conversions.path_msg([], [], self.opt.frame_id, meta.stamp_ns)
            self.pub_loop.publish(verdict)

    def _detect(self, meta: KeyframeMeta, parts: dict) -> Path | None:
        """Add the keyframe and run the loop query; the corrected poses when a loop is applied."""
        kid = meta.keyframe_id
        if self.closer is None:
            return None
        if kid != len(self._poses):
            raise RuntimeError(f"keyframe {kid} arrived after {len(self._poses)} keyframes: ids out of step")
        frame = KeyframeSubscriber.frame(parts)
        self._poses.append(np.array(meta.T_world_cam, dtype=np.float64))
        self._stamps.append(int(meta.stamp_ns))
        self.closer.add_keyframe(kid, frame)
        event, corrected = self.closer.close(kid, np.stack(self._poses), frame)
        if event is None:
            return None
        self.n_detected += 1
        frames = f"keyframe {kid} (frame {meta.frame_index}) with keyframes {list(event.loop_ids)}"
        if not event.applied:
            self.get_logger().info(f"loop {frames} not applied: {event.reason}")
            return None
        self.n_loops += 1
        first = event.start_id + 1
        self._poses[first:] = list(corrected[first:])
        with self.cond:
            self._sent_loop_stamp = int(meta.stamp_ns)
            self._mapper_poses = None  # received before the correction: stale already
        self.get_logger().info(
            f"loop {frames}: score {event.score:.3f}, correction {event.correction_cm:.1f} cm / "
            f"{event.correction_deg:.2f} deg, keyframes {first}..{kid} corrected"
        )
        return conversions.path_msg(
            np.array(self._stamps[first:], dtype=np.int64), corrected[first:], self.opt.frame_id, meta.stamp_ns
        )

    # ------------------------------------------------------------------ shutdown

    def finish(self) -> None:
        self.final_log(
            f"neb_slam loop_closer stopped: {len(self._poses)} keyframes, {self.n_detected} loops "
            f"detected, {self.n_loops} applied"
        )


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``loop_closer`` executable; returns the exit status."""
    return run_node(LoopCloserNode, args)


if __name__ == "__main__":
    sys.exit(main())
