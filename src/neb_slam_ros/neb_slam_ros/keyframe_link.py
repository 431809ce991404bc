"""The keyframe hand-over between the tracker and the mapper: what travels, and its assembly by stamp.

A keyframe is five messages with the same stamp: ``keyframe/rgb`` (rgb8), ``keyframe/depth`` (32FC1 metres,
exact), ``keyframe/camera_info`` (the rectified camera: no distortion), ``keyframe/pose`` (PoseStamped)
and ``keyframe/meta`` (std_msgs/String, JSON) with what the standard messages cannot carry:

    {"stamp_ns": int, "frame_index": int, "keyframe_id": int, "map_now": bool, "first": bool,
     "T_world_cam": [16 floats, row-major, exact], "block_centres": [[x, y, z], ...],
     "T_map_world": [16 floats] (the first keyframe only), "first_iterations": int (the first keyframe only)}

``block_centres`` lists every block the tracker has allocated so far (ids are positions), so a mapper
creates the same blocks before it integrates the keyframe, whatever order the topics arrive in.
``T_map_world`` is the engine world's pose in the tracker's level ``map_frame`` (:mod:`neb_slam_ros.frames`),
fixed at the first frame: the mapper publishes its mesh in that frame too. ``first_iterations`` is the
number of map-only steps the tracker waits for on the first keyframe (the mapper runs the rest of
``mapping.first_iterations`` in the background); absent: all of them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

KEYFRAME_PARTS = ("rgb", "depth", "camera_info", "pose", "meta")


@dataclass
class KeyframeMeta:
    stamp_ns: int
    frame_index: int
    keyframe_id: int
    map_now: bool
    first: bool
    T_world_cam: np.ndarray
    block_centres: np.ndarray
    T_map_world: np.ndarray | None = None
    first_iterations: int | None = None

    def to_json(self) -> str:
        extra = {}
        if self.T_map_world is not None:
            extra["T_map_world"] = [float(v) for v in np.asarray(self.T_map_world).reshape(-1)]
        if self.first_iterations is not None:
            extra["first_iterations"] = int(self.first_iterations)
        return json.dumps(
            {
                "stamp_ns": self.stamp_ns,
                "frame_index": self.frame_index,
                "keyframe_id": self.keyframe_id,
                "map_now": self.map_now,
                "first": self.first,
                "T_world_cam": [float(v) for v in np.asarray(self.T_world_cam).reshape(-1)],
                "block_centres": np.asarray(self.block_centres, dtype=np.float64).reshape(-1, 3).tolist(),
                **extra,
            }
        )

    @classmethod
    def from_json(cls, text: str) -> KeyframeMeta:
        """Parse; raises ValueError naming the field that is missing or wrong."""
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"not JSON: {exc}") from None
        try:
            T = np.array(d["T_world_cam"], dtype=np.float64).reshape(4, 4)
            centres = np.array(d["block_centres"], dtype=np.float64).reshape(-1, 3)
            T_map_world = np.array(d["T_map_world"], dtype=np.float64).reshape(4, 4) if "T_map_world" in d else None
            return cls(
                int(d["stamp_ns"]),
                int(d["frame_index"]),
                int(d["keyframe_id"]),
                bool(d["map_now"]),
                bool(d["first"]),
                T,
                centres,
                T_map_world,
                int(d["first_iterations"]) if "first_iterations" in d else None,
            )
        except KeyError as exc:
            raise ValueError(f"field {exc.args[0]!r} is missing") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"a field has the wrong type or shape: {exc}") from None


class KeyframeAssembler:
    """Collects the five parts of each keyframe by stamp and hands out complete keyframes in keyframe-id
    order (a keyframe whose predecessor is still incomplete waits for it); a keyframe that comes again
    after it was handed out (a tracker sends keyframes again to a restarted mapper) is dropped."""

    def __init__(self, capacity: int = 200):
        self.capacity = capacity
        self._parts: dict[int, dict[str, object]] = {}
        self._complete: dict[int, dict[str, object]] = {}  # keyframe id -> parts
        self.next_id = 0

    def add(self, part: str, stamp_ns: int, value) -> None:
        parts = self._parts.setdefault(stamp_ns, {})
        parts[part] = value
        if len(parts) == len(KEYFRAME_PARTS):
            del self._parts[stamp_ns]
            if parts["meta"].keyframe_id >= self.next_id:  # lower: sent again, and handed on already
                self._complete[parts["meta"].keyframe_id] = parts
        while len(self._parts) > self.capacity:  # parts whose siblings never came
            del self._parts[min(self._parts)]

    def pop_ready(self) -> list[dict[str, object]]:
        """Complete keyframes that are next in order."""
        out = []
        while self.next_id in self._complete:
            out.append(self._complete.pop(self.next_id))
            self.next_id += 1
        return out

    @property
    def has_ready(self) -> bool:
        """The next keyframe in order is complete."""
        return self.next_id in self._complete

    @property
    def n_waiting(self) -> int:
        return len(self._parts) + len(self._complete)


class KeyframeSubscriber:
    """A node's ``keyframe/*`` subscriptions (the mapper's and the loop closer's input): the parts go into
    :attr:`assembler` under the node's condition variable, which is notified; a worker thread pops complete
    keyframes in order and turns them into frames with :meth:`frame`."""

    def __init__(self, node, cond):
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import CameraInfo, Image
        from std_msgs.msg import String

        from neb_slam_ros import qos

        self.node = node
        self._cond = cond
        self.assembler = KeyframeAssembler()
        kinds = {"rgb": Image, "depth": Image, "camera_info": CameraInfo, "pose": PoseStamped, "meta": String}
        for part in KEYFRAME_PARTS:
            node.create_subscription(
                kinds[part], f"keyframe/{part}", lambda m, p=part: self._on_part(p, m), qos.keyframes()
            )

    def _on_part(self, part: str, msg) -> None:
        from neb_slam_ros import conversions

        topic = self.node.resolve_topic_name(f"keyframe/{part}")
        if part == "meta":
            try:
                meta = KeyframeMeta.from_json(msg.data)
            except ValueError as exc:
                self.node.get_logger().error(f"{topic}: {exc}: keyframe ignored")
                return
            stamp, value = meta.stamp_ns, meta
        else:
            stamp, value = conversions.stamp_ns(msg), msg
        with self._cond:
            self.assembler.add(part, stamp, value)
            self._cond.notify_all()

    @staticmethod
    def frame(parts: dict):
        """The keyframe's :class:`~neb_slam_core.types.RgbdFrame` (rectified, as the tracker tracked it)."""
        from neb_slam_ros import conversions

        meta: KeyframeMeta = parts["meta"]
        camera = conversions.camera_from_msg(parts["camera_info"], "keyframe/camera_info")
        topics = ("keyframe/rgb", "keyframe/depth", "keyframe/camera_info")
        frame, _ = conversions.frame_from_msgs(parts["rgb"], parts["depth"], camera, 1.0, topics, meta.frame_index)
        return frame
