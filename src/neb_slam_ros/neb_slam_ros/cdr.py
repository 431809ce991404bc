"""Serialized ROS messages built straight from numpy arrays: the large outputs (``mesh``, ``path``).

rclpy fills a message's sequence of nested messages (a marker's ``points``, a path's ``poses``) only from
one Python object per element, which costs microseconds per point. ``Publisher.publish`` also takes a
message already serialized (``bytes``), so these writers lay out the message's CDR form (the
little-endian encoding of the ROS 2 middlewares: a 4-byte encapsulation header, then every field aligned
to its size, counted from the end of that header) with the arrays copied in whole.

:func:`supported` checks once per process that the middleware in use reads these bytes back as the
messages they describe (its own deserializer on a sample of each kind); when it does not, callers build
message objects instead.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Mapping

import numpy as np

#: CDR, little endian, no options
ENCAPSULATION = b"\x00\x01\x00\x00"

MARKER_NS = "neb_blocks"
TRIANGLE_LIST = 11  # visualization_msgs/Marker.TRIANGLE_LIST
ADD, DELETE = 0, 2  # visualization_msgs/Marker.ADD, DELETE


class CdrWriter:
    """Appends CDR fields; :meth:`data` is the serialized message (encapsulation header included)."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []
        self._size = 0  # bytes after the encapsulation header: alignment counts from there

    def _put(self, data) -> None:
        self._parts.append(data)
        self._size += len(data)

    def align(self, n: int) -> None:
        pad = -self._size % n
        if pad:
            self._put(b"\x00" * pad)

    def pack(self, fmt: str, *values, align: int) -> None:
        """``values`` packed as ``struct`` format ``fmt`` (little endian), after aligning to ``align``."""
        self.align(align)
        self._put(struct.pack("<" + fmt, *values))

    def boolean(self, value: bool) -> None:
        self._put(b"\x01" if value else b"\x00")

    def string(self, text: str) -> None:
        raw = text.encode() + b"\x00"
        self.pack("I", len(raw), align=4)
        self._put(raw)

    def time(self, ns: int) -> None:
        """builtin_interfaces/Time (or Duration) of ``ns`` nanoseconds."""
        sec, nanosec = divmod(int(ns), 1_000_000_000)
        self.pack("iI", sec, nanosec, align=4)

    def header(self, ns: int, frame_id: str) -> None:
        self.time(ns)
        self.string(frame_id)

    def array(self, a: np.ndarray, align: int) -> None:
        """The bytes of array ``a`` (already of the wire's dtype), after aligning to ``align`` when not empty
        (an empty sequence of structs has no element to align)."""
        if a.size:
            self.align(align)
            self._put(memoryview(np.ascontiguousarray(a).reshape(-1).view(np.uint8)))

    def data(self) -> bytes:
        return ENCAPSULATION + b"".join(self._parts)


# ---------------------------------------------------------------------------------------------- mesh


def _marker(w: CdrWriter, block_id: int, ns: int, frame_id: str, tri: tuple[np.ndarray, np.ndarray] | None) -> None:
    """One visualization_msgs/Marker: block ``block_id``'s TRIANGLE_LIST (``tri``: points, colors), or its
    DELETE (``tri`` None, no points)."""
    w.header(ns, frame_id)
    w.string(MARKER_NS)
    w.pack("iii", int(block_id), TRIANGLE_LIST, ADD if tri is not None else DELETE, align=4)
    w.pack("7d", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, align=8)  # pose: identity
    w.pack("3d", 1.0, 1.0, 1.0, align=8)  # scale
    w.pack("4f", 1.0, 1.0, 1.0, 1.0, align=4)  # color: white (the vertex colours apply)
    w.time(0)  # lifetime: forever
    w.boolean(False)  # frame_locked
    points, colors = tri if tri is not None else (np.zeros((0, 3)), np.zeros((0, 4), np.float32))
    w.pack("I", len(points), align=4)
    w.array(np.asarray(points, dtype="<f8"), 8)
    w.pack("I", len(colors), align=4)
    w.array(np.asarray(colors, dtype="<f4"), 4)
    w.string("")  # texture_resource
    w.header(0, "")  # texture (sensor_msgs/CompressedImage): header,
    w.string("")  # format,
    w.pack("I", 0, align=4)  # data
    w.pack("I", 0, align=4)  # uv_coordinates
    w.string("")  # text
    w.string("")  # mesh_resource
    w.string("")  # mesh_file: filename,
    w.pack("I", 0, align=4)  # data
    w.boolean(False)  # mesh_use_embedded_materials


def mesh_marker_array(parts: Mapping[int, tuple[np.ndarray, np.ndarray] | None], ns: int, frame_id: str) -> bytes:
    """A serialized visualization_msgs/MarkerArray: per block id (ascending), its TRIANGLE_LIST marker
    (ns :data:`MARKER_NS`, id = block id, identity pose, unit scale, white, the ``(points, colors)`` of
    :func:`~neb_slam_ros.conversions.triangle_list`), or a DELETE marker where the part is None; every
    header stamped ``ns``."""
    w = CdrWriter()
    w.pack("I", len(parts), align=4)
    for block_id in sorted(parts):
        _marker(w, block_id, ns, frame_id, parts[block_id])
    return w.data()


# ---------------------------------------------------------------------------------------------- path


def pose_rows(poses: np.ndarray) -> np.ndarray:
    """``(N, 7)`` float64 rows x, y, z, qx, qy, qz, qw of ``(N, 4, 4)`` poses (geometry_msgs/Pose order)."""
    from neb_slam_core.geometry.se3 import pose_to_tum

    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    return pose_to_tum(poses).reshape(-1, 7) if len(poses) else np.zeros((0, 7))


def path(stamps_ns: np.ndarray, rows: np.ndarray, frame_id: str, stamp_ns: int) -> bytes:
    """A serialized nav_msgs/Path stamped ``stamp_ns`` of poses ``rows`` (:func:`pose_rows`), each a
    PoseStamped stamped with its entry of ``stamps_ns``, all in ``frame_id``."""
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    rows = np.asarray(rows, dtype="<f8").reshape(-1, 7)
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.pack("I", len(stamps), align=4)
    if len(stamps) == 0:
        return w.data()
    # the first PoseStamped starts wherever the header left off; it ends on its float64 pose, so every
    # later one starts 8-aligned and has the same layout: those go in as one structured array
    w.header(int(stamps[0]), frame_id)
    w.pack("7d", *rows[0], align=8)
    name = frame_id.encode() + b"\x00"
    pose_at = -(-(12 + len(name)) // 8) * 8
    record = np.dtype(
        {
            "names": ["sec", "nanosec", "length", "name", "pose"],
            "formats": ["<i4", "<u4", "<u4", ("u1", len(name)), ("<f8", 7)],
            "offsets": [0, 4, 8, 12, pose_at],
            "itemsize": pose_at + 56,
        }
    )
    rest = np.zeros(len(stamps) - 1, dtype=record)
    sec, nanosec = np.divmod(stamps[1:], 1_000_000_000)
    rest["sec"], rest["nanosec"], rest["length"] = sec, nanosec, len(name)
    rest["name"] = np.frombuffer(name, dtype=np.uint8)
    rest["pose"] = rows[1:]
    w.array(rest, 8)
    return w.data()


# ---------------------------------------------------------------------------------------------- check


@functools.cache
def supported() -> bool:
    """The middleware in use deserializes these writers' bytes into the messages they describe (checked
    once, on a marker array with a triangle list, a DELETE and an odd-length frame id, and on a path)."""
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    from neb_slam_ros import conversions

    verts = np.array([[0.0, 1.0, 2.0], [3.5, -1.0, 0.25], [1.0, 1.0, 1.0]])
    faces = np.array([[0, 1, 2], [2, 1, 0]])
    colours = np.array([[255, 0, 7], [1, 2, 3], [128, 64, 32]], dtype=np.uint8)
    parts = {4: conversions.triangle_list(verts, faces, colours), 9: None}
    ns = 12_345_678_901
    try:
        for frame_id in ("map", "world_frame"):
            expected = conversions.mesh_marker_msgs(parts, ns, frame_id)
            data = mesh_marker_array(parts, ns, frame_id)
            if len(data) != len(serialize_message(expected)) or deserialize_message(data, MarkerArray) != expected:
                return False
            poses = np.tile(np.eye(4), (3, 1, 1))
            poses[:, :3, 3] = verts
            stamps = np.array([5, 1_000_000_007, 2_500_000_000])
            expected_path = conversions.path_msg(stamps, poses, frame_id, ns)
            data = path(stamps, pose_rows(poses), frame_id, ns)
            if len(data) != len(serialize_message(expected_path)):
                return False
            if deserialize_message(data, type(expected_path)) != expected_path:
                return False
    except Exception:  # a middleware that refuses the bytes
        return False
    return True
