"""The camera input of the ``tracker`` and ``slam`` nodes: colour, depth and camera info in, checked
:class:`~neb_slam_core.types.RgbdFrame` out; every bad message is a counted, throttled warning naming the
topic, never an exception.

Inputs (relative names, remappable): ``rgb/image`` (rgb8, bgr8, rgba8, bgra8, mono8), ``depth/image``
(16UC1 or mono16 in units of ``depth_scale`` metres, or 32FC1 metres) and ``rgb/camera_info``. Colour and
depth are paired by stamp (exact, or nearest within ``sync_slop_s``; the frame takes the depth image's stamp,
or the colour image's: ``frame_stamp``); stamps must increase. Depth follows
REP 118: NaN and Inf pixels are invalid readings, a frame without any valid depth is skipped.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from neb_slam_core.datasets.base import FRAME_STAMPS
from neb_slam_core.types import RgbdFrame
from neb_slam_ros import conversions, qos
from neb_slam_ros.params import require
from neb_slam_ros.sync import StampPairer


@dataclass(frozen=True)
class InputOptions:
    """Parameters of the camera input (shared by ``tracker`` and ``slam``)."""

    depth_scale: float = 0.001
    sync_slop_s: float = 0.02
    frame_stamp: str = "depth"
    reliable_inputs: bool = False
    frame_queue: int = 30
    ground_truth_topic: str = ""
    warn_period_s: float = 5.0

    PARAMETER_DOCS = {
        "depth_scale": "metres per unit of 16UC1/mono16 depth images (32FC1 is metres)",
        "sync_slop_s": "colour and depth are paired by stamp: exact, or nearest within this",
        "frame_stamp": "which image's stamp a pair's frame (its pose, TF and outputs) takes: depth (the image that "
        "fixes the geometry) or colour",
        "reliable_inputs": "camera subscriptions reliable (lossless replay) instead of sensor-data QoS",
        "frame_queue": "frames kept while the engine is busy (beyond it one is dropped, with a warning: the "
        "oldest, or for a live engine the one whose neighbours lie closest in time); a live engine catching "
        "up after a wait tracks from these (live.max_gap_s)",
        "ground_truth_topic": "PoseStamped topic with the camera's ground truth (e.g. ground_truth/pose): the "
        "first frame starts from its pose; empty: from the identity",
        "warn_period_s": "throttle of repeated input warnings",
    }

    def check(self) -> None:
        require(self.depth_scale > 0, "depth_scale", "> 0", self.depth_scale)
        require(self.sync_slop_s >= 0, "sync_slop_s", ">= 0", self.sync_slop_s)
        require(self.frame_stamp in FRAME_STAMPS, "frame_stamp", f"one of {', '.join(FRAME_STAMPS)}", self.frame_stamp)
        require(self.frame_queue >= 1, "frame_queue", ">= 1", self.frame_queue)
        require(self.warn_period_s >= 0, "warn_period_s", ">= 0", self.warn_period_s)


class InputWarnings:
    """Counted, throttled warnings about bad input: one line per topic and problem kind per period."""

    def __init__(self, logger, period_s: float):
        self.logger = logger
        self.period_s = period_s
        self.counts: dict[str, int] = {}
        self._last: dict[str, float] = {}

    def warn(self, key: str, text: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self.period_s:
            self._last[key] = now
            self.logger.warning(f"{text} ({self.counts[key]} so far)")

    @property
    def total(self) -> int:
        return sum(self.counts.values())


class CameraInput:
    """Subscribes the camera topics on ``node`` and queues every usable frame for the node's worker thread:
    at most ``frame_queue`` of them, one dropped with a counted warning when the worker falls behind.

    Which one: an engine that processes every frame in order (``thin`` False) loses the oldest. A live
    engine (``thin``) catches up after a wait in steps of at most ``live.max_gap_s`` from the last frame it
    processed, so the queue keeps its frames spread over the wait: it drops the frame whose neighbours
    (for the oldest: the last frame taken) lie closest in time, the oldest of equals, never the newest. A
    wait of any length then leaves frames at even steps from where the engine stopped to now, where
    dropping the oldest would leave only the last ``frame_queue`` frames and a jump to them.

    The queue is guarded by ``cond`` (the node's condition variable, notified on each frame); the
    worker takes frames with :meth:`pop` while holding it. Ground-truth poses, when
    ``ground_truth_topic`` is set, are kept by stamp for :meth:`ground_truth_near`."""

    HELD_FOR_CAMERA_INFO = 3

    def __init__(self, node: Node, opt: InputOptions, cond: threading.Condition, thin: bool = False):
        self.node = node
        self.opt = opt
        self.thin = thin
        self._cond = cond
        self._queue: deque[RgbdFrame] = deque()
        self._last_taken_ns: int | None = None  # stamp of the last frame the engine took
        self.n_dropped = 0
        self.warnings = InputWarnings(node.get_logger(), opt.warn_period_s)
        self.topics = tuple(node.resolve_topic_name(t) for t in ("rgb/image", "depth/image", "rgb/camera_info"))
        self.slop_ns = int(round(opt.sync_slop_s * 1e9))
        self._pairer = StampPairer(self.slop_ns, frame_stamp=opt.frame_stamp)
        self._camera = None
        self._held: list = []  # frames that came before any camera info
        self.n_accepted = 0
        self.frame_id = ""  # the colour images' header.frame_id (the camera's optical frame)
        self._told_nan = False
        self._ground_truth: dict[int, np.ndarray] = {}
        cam = qos.camera(opt.reliable_inputs)
        node.create_subscription(Image, "rgb/image", lambda m: self._on_image("rgb", m), cam)
        node.create_subscription(Image, "depth/image", lambda m: self._on_image("depth", m), cam)
        node.create_subscription(CameraInfo, "rgb/camera_info", self._on_camera_info, cam)
        if opt.ground_truth_topic:
            node.create_subscription(PoseStamped, opt.ground_truth_topic, self._on_ground_truth, qos.events())

    # ------------------------------------------------------------------ the queue

    def _enqueue(self, frame: RgbdFrame) -> None:
        with self._cond:
            self._queue.append(frame)
            if len(self._queue) > self.opt.frame_queue:
                i = self._to_drop()
                del self._queue[i]
                self.n_dropped += 1
                which = "oldest queued frame" if i == 0 else "a queued frame (the queue keeps them spread)"
                self.warnings.warn(
                    "queue",
                    f"{self.node.get_name()} is behind the input: {which} dropped ({self.n_dropped} dropped)",
                )
            self._cond.notify_all()

    def _to_drop(self) -> int:
        """The index of the queued frame a full queue drops (class docstring)."""
        if not self.thin or len(self._queue) < 3:
            return 0
        stamps = np.array([f.stamp_ns for f in self._queue], dtype=np.int64)
        before = np.concatenate([[stamps[0] if self._last_taken_ns is None else self._last_taken_ns], stamps[:-2]])
        # the gap left where frame i was, for every frame but the newest; argmin takes the oldest of equals
        return int(np.argmin(stamps[1:] - before))

    @property
    def has_frame(self) -> bool:
        """A frame is queued (read with the condition held)."""
        return bool(self._queue)

    @property
    def queued(self) -> int:
        """Frames waiting for the engine."""
        return len(self._queue)

    def pop(self) -> RgbdFrame | None:
        """The oldest queued frame, or None (call with the condition held)."""
        return self._take() if self._queue else None

    def _take(self) -> RgbdFrame:
        frame = self._queue.popleft()
        self._last_taken_ns = frame.stamp_ns
        return frame

    def drop_queued(self) -> int:
        """Drop (and count) every queued frame: at shutdown, frames the engine will never process. Returns
        how many (call with the condition held)."""
        n = len(self._queue)
        self.n_dropped += n
        self._queue.clear()
        return n

    def pop_newest(self) -> RgbdFrame | None:
        """The newest queued frame, or None; the older ones are dropped and counted (call with the
        condition held)."""
        return self.pop_chosen(lambda stamps: len(stamps) - 1)

    def pop_chosen(self, choose: Callable[[list[int]], int]) -> RgbdFrame | None:
        """The queued frame ``choose`` picks from the queued frames' stamps (oldest first; it returns an
        index), or None when none is queued; the older ones are dropped and counted, the newer stay
        queued (call with the condition held). A live engine picks with ``LiveSlam.next_frame``."""
        if not self._queue:
            return None
        i = choose([f.stamp_ns for f in self._queue])
        if not 0 <= i < len(self._queue):
            raise IndexError(f"pop_chosen: index {i} outside the {len(self._queue)} queued frames")
        for _ in range(i):
            self._queue.popleft()
        self.n_dropped += i
        return self._take()

    def push_front(self, frame: RgbdFrame) -> None:
        """Queue ``frame`` again as the oldest (a frame taken, then not processed yet; condition held)."""
        self._queue.appendleft(frame)

    # ------------------------------------------------------------------ callbacks (executor thread)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self._camera = conversions.camera_from_msg(msg, self.topics[2])
        except conversions.InputError as exc:
            self.warnings.warn(f"info:{exc.problem[:40]}", f"{exc}: camera info ignored")
            return
        held, self._held = self._held, []
        self._accept(held)

    def _on_image(self, stream: str, msg: Image) -> None:
        topic = self.topics[0 if stream == "rgb" else 1]
        pairs, refused = self._pairer.push(stream, conversions.stamp_ns(msg), msg)
        if refused:
            self.warnings.warn(f"{stream}:order", f"{topic}: {refused}: message skipped")
        if self._camera is None and pairs:
            # topics arrive in any order: the first frames may come before the camera info, so a few are
            # held for it; beyond that they are dropped with the warning that names the missing topic
            self._held += pairs
            while len(self._held) > self.HELD_FOR_CAMERA_INFO:
                pair = self._held.pop(0)
                self.warnings.warn(
                    "no_info",
                    f"{self.topics[1]}: no camera info received yet on {self.topics[2]}: frame {pair.stamp_ns} skipped",
                )
            return
        self._accept(pairs)

    def _accept(self, pairs) -> None:
        for pair in pairs:
            try:
                frame, n_nan = conversions.frame_from_msgs(
                    pair.rgb,
                    pair.depth,
                    self._camera,
                    self.opt.depth_scale,
                    self.topics,
                    self.n_accepted,
                    self.opt.frame_stamp,
                )
            except conversions.InputError as exc:
                self.warnings.warn(f"{exc.topic}:{exc.problem[:40]}", f"{exc}: frame {pair.stamp_ns} skipped")
                continue
            if n_nan and not self._told_nan:
                # NaN is how 32FC1 depth marks "no reading" (REP 118): normal, so said once, not warned
                self._told_nan = True
                self.node.get_logger().info(
                    f"{self.topics[1]}: {n_nan} depth pixels NaN or Inf in frame "
                    f"{frame.stamp_ns}: read as invalid (REP 118), here and from now on"
                )
            self.n_accepted += 1
            self.frame_id = pair.rgb.header.frame_id
            self._enqueue(frame)

    def _on_ground_truth(self, msg: PoseStamped) -> None:
        try:
            T = conversions.pose_from_msg(msg, self.opt.ground_truth_topic)
        except conversions.InputError as exc:
            self.warnings.warn("ground_truth", f"{exc}: ignored")
            return
        self._ground_truth[conversions.stamp_ns(msg)] = T
        while len(self._ground_truth) > 10_000:
            del self._ground_truth[min(self._ground_truth)]

    def ground_truth_near(self, stamp_ns: int) -> np.ndarray | None:
        """The ground-truth pose within ``sync_slop_s`` of ``stamp_ns`` (nearest), or None."""
        near = [s for s in list(self._ground_truth) if abs(s - stamp_ns) <= self.slop_ns]
        return self._ground_truth[min(near, key=lambda s: abs(s - stamp_ns))] if near else None

    def wait_for_ground_truth(self, stamp_ns: int, timeout_s: float, stop: Callable[[], bool]) -> np.ndarray | None:
        """:meth:`ground_truth_near`, waiting up to ``timeout_s`` for it (topics arrive in any order)."""
        deadline = time.monotonic() + timeout_s
        while True:
            T = self.ground_truth_near(stamp_ns)
            if T is not None or time.monotonic() >= deadline or stop():
                return T
            time.sleep(0.05)
