"""Pure conversions between ROS messages and the core's types (no node state, no I/O).

Decoding reuses the core's bag decoders (``neb_slam_core.io.bag``), which read rclpy messages as well as
rosbags ones (same field names). Every decoding problem is an :class:`InputError` naming the topic.
"""

from __future__ import annotations

import array

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, TransformStamped, Twist, Vector3
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from neb_slam_core.datasets.base import frame_stamps
from neb_slam_core.geometry.se3 import invert, pose_from_tum, pose_to_tum
from neb_slam_core.io.bag import decode_depth_m, decode_rgb, intrinsics_from_camera_info
from neb_slam_core.io.bag import pose_from_msg as bag_pose_from_msg
from neb_slam_core.types import COLOUR_STAMP, DEPTH_STAMP, Intrinsics, RgbdFrame


class InputError(Exception):
    """A message on ``topic`` cannot be used; ``problem`` says why (the frame is skipped)."""

    def __init__(self, topic: str, problem: str):
        self.topic = topic
        self.problem = problem
        super().__init__(f"{topic}: {problem}")


def map_update_from_msg(msg, node):
    """The :class:`~neb_slam_core.scene.map_update.MapUpdate` in a ``map_update`` message, or None (with
    an error logged by ``node`` naming the topic) when it cannot be decoded."""
    from neb_slam_core.scene import map_update

    try:
        return map_update.decode(msg.data)
    except map_update.MapUpdateError as exc:
        node.get_logger().error(f"{node.resolve_topic_name('map_update')}: {exc}: update ignored")
        return None


# ---------------------------------------------------------------------------------------------- time


def stamp_ns(msg) -> int:
    """``header.stamp`` as integer nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def to_time(ns: int) -> Time:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def header(ns: int, frame_id: str) -> Header:
    return Header(stamp=to_time(ns), frame_id=frame_id)


# ---------------------------------------------------------------------------------------------- input


def camera_from_msg(msg: CameraInfo, topic: str) -> tuple[Intrinsics, tuple[float, ...]]:
    """CameraInfo -> intrinsics and distortion D (plumb_bob, or none)."""
    try:
        intr, d = intrinsics_from_camera_info(msg)
    except ValueError as exc:
        raise InputError(topic, str(exc)) from None
    if any(d) and msg.distortion_model not in ("plumb_bob", "rational_polynomial"):
        raise InputError(
            topic,
            f"distortion model {msg.distortion_model!r} is not supported (expected plumb_bob or rational_polynomial)",
        )
    return intr, d


def frame_from_msgs(
    rgb_msg: Image,
    depth_msg: Image,
    camera: tuple[Intrinsics, tuple[float, ...]] | None,
    depth_scale: float,
    topics: tuple[str, str, str],
    index: int = 0,
    frame_stamp: str = "depth",
) -> tuple[RgbdFrame, int]:
    """One RGB-D frame from its colour and depth images and the latest camera info, stamped with the
    ``frame_stamp`` image's stamp (:data:`~neb_slam_core.datasets.base.FRAME_STAMPS`; both stamps are in
    its ``extras``).

    ``topics``: the colour, depth and camera-info topic names (for messages). Depth follows REP 118:
    NaN, +-Inf, 0 and negative readings are invalid (0 in the frame). Returns the frame and how many of
    its depth pixels were not finite. Raises :class:`InputError` when the frame cannot be used.
    """
    rgb_topic, depth_topic, info_topic = topics
    if camera is None:
        raise InputError(depth_topic, f"no camera info received yet on {info_topic}: the frame is skipped")
    intr, distortion = camera
    try:
        rgb = decode_rgb(rgb_msg)
    except ValueError as exc:
        raise InputError(rgb_topic, str(exc)) from None
    try:
        depth = decode_depth_m(depth_msg, depth_scale)
    except ValueError as exc:
        raise InputError(depth_topic, str(exc)) from None
    size = (intr.width, intr.height)
    for topic, img in ((rgb_topic, rgb), (depth_topic, depth)):
        if (img.shape[1], img.shape[0]) != size:
            raise InputError(topic, f"image is {img.shape[1]}x{img.shape[0]} but {info_topic} says {size[0]}x{size[1]}")
    n_not_finite = 0
    if depth_msg.encoding == "32FC1":
        raw = np.frombuffer(memoryview(depth_msg.data), dtype=np.uint8)
        n_not_finite = int((~np.isfinite(raw[: raw.size - raw.size % 4].view(np.float32))).sum())
    if not (depth > 0).any():
        raise InputError(depth_topic, "no valid depth pixel (all 0, NaN, Inf or negative)")
    extras = {"distortion": distortion} if any(distortion) else {}
    extras[COLOUR_STAMP], extras[DEPTH_STAMP] = stamp_ns(rgb_msg), stamp_ns(depth_msg)
    stamp = frame_stamps(extras[COLOUR_STAMP], extras[DEPTH_STAMP], frame_stamp)
    return RgbdFrame(index=index, stamp_ns=stamp, rgb=rgb, depth_m=depth, intrinsics=intr, extras=extras), n_not_finite


def pose_from_msg(msg: PoseStamped, topic: str) -> np.ndarray:
    """PoseStamped -> ``(4, 4)`` pose; a non-finite pose or a quaternion far from unit length is refused."""
    try:
        return bag_pose_from_msg(msg)
    except ValueError as exc:
        raise InputError(topic, str(exc)) from None


def transform_from_msg(msg) -> np.ndarray:
    """geometry_msgs/TransformStamped -> ``(4, 4)`` pose of the child frame in the parent frame."""
    v, q = msg.transform.translation, msg.transform.rotation
    return pose_from_tum(np.array([v.x, v.y, v.z, q.x, q.y, q.z, q.w]))


# ---------------------------------------------------------------------------------------------- output


def transform_msg(T: np.ndarray, ns: int, parent: str, child: str) -> TransformStamped:
    """``(4, 4)`` pose of ``child`` in ``parent`` -> geometry_msgs/TransformStamped stamped ``ns``."""
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in pose_to_tum(T))
    return TransformStamped(
        header=header(ns, parent),
        child_frame_id=child,
        transform=Transform(translation=Vector3(x=tx, y=ty, z=tz), rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
    )


def _bytes(a: np.ndarray) -> array.array:
    """Fast fill of a uint8[] message field (rclpy checks a list element by element)."""
    return array.array("B", np.ascontiguousarray(a).view(np.uint8).reshape(-1).tobytes())


def rgb_msg(rgb: np.ndarray, ns: int, frame_id: str) -> Image:
    h, w = rgb.shape[:2]
    return Image(
        header=header(ns, frame_id),
        height=h,
        width=w,
        encoding="rgb8",
        is_bigendian=0,
        step=3 * w,
        data=_bytes(rgb.astype(np.uint8, copy=False)),
    )


def depth_msg(depth_m: np.ndarray, ns: int, frame_id: str) -> Image:
    """32FC1 metres with NaN where invalid (REP 118): exact for any float32 depth."""
    h, w = depth_m.shape
    d = depth_m.astype("<f4", copy=True)
    d[~(np.isfinite(d) & (d > 0))] = np.nan
    return Image(
        header=header(ns, frame_id), height=h, width=w, encoding="32FC1", is_bigendian=0, step=4 * w, data=_bytes(d)
    )


def camera_info_msg(intr: Intrinsics, distortion, ns: int, frame_id: str) -> CameraInfo:
    d = [float(v) for v in (distortion if distortion is not None and len(distortion) else [0.0] * 5)]
    K = intr.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    return CameraInfo(
        header=header(ns, frame_id),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob",
        d=d,
        k=[float(v) for v in K.reshape(-1)],
        r=[float(v) for v in np.eye(3).reshape(-1)],
        p=[float(v) for v in P.reshape(-1)],
    )


def pose_msg(T_world_cam: np.ndarray, ns: int, frame_id: str) -> PoseStamped:
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in pose_to_tum(T_world_cam))
    return PoseStamped(
        header=header(ns, frame_id),
        pose=Pose(position=Point(x=tx, y=ty, z=tz), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
    )


#: the variance (m^2 and rad^2) on the diagonal of a pose without a covariance (tracking failed and the
#: pose is the motion prediction): large enough that a filter fusing it gives it no weight, the value
#: rtabmap_ros publishes for a lost odometry
UNKNOWN_VARIANCE = 9999.0


def covariance_field(covariance: np.ndarray | None) -> list[float]:
    """The 36 row-major floats of a ROS pose covariance over (x, y, z, rot x, rot y, rot z) from a 6x6
    matrix in that order; None (no estimate) gives :data:`UNKNOWN_VARIANCE` on the diagonal."""
    if covariance is None:
        covariance = np.diag(np.full(6, UNKNOWN_VARIANCE))
    return [float(v) for v in np.asarray(covariance, dtype=np.float64).reshape(36)]


def odometry_msg(
    T_world_cam: np.ndarray,
    ns: int,
    T_prev: np.ndarray | None,
    prev_ns: int | None,
    frame_id: str,
    child_frame_id: str,
    covariance: np.ndarray | None = None,
) -> Odometry:
    """Pose with its ``covariance`` (:func:`covariance_field`) plus the twist (in the camera frame, as
    nav_msgs/Odometry wants) from the previous pose."""
    msg = Odometry(header=header(ns, frame_id), child_frame_id=child_frame_id)
    msg.pose.pose = pose_msg(T_world_cam, ns, frame_id).pose
    msg.pose.covariance = covariance_field(covariance)
    if T_prev is not None and prev_ns is not None and ns > prev_ns:
        dt = (ns - prev_ns) * 1e-9
        delta = invert(T_prev) @ T_world_cam  # motion in the previous camera frame
        from scipy.spatial.transform import Rotation

        w = Rotation.from_matrix(delta[:3, :3]).as_rotvec() / dt
        v = delta[:3, 3] / dt
        msg.twist.twist = Twist(
            linear=Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2])),
            angular=Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2])),
        )
    return msg


def path_msg(stamps_ns, poses, frame_id: str, stamp_ns: int | None = None) -> Path:
    """A Path of ``poses`` (each stamped); its header has ``stamp_ns`` (default: the last pose's, else 0)."""
    if stamp_ns is None:
        stamp_ns = int(stamps_ns[-1]) if len(stamps_ns) else 0
    msg = Path(header=header(int(stamp_ns), frame_id))
    msg.poses = [pose_msg(T, int(s), frame_id) for s, T in zip(stamps_ns, poses)]
    return msg


def block_markers(
    centres: np.ndarray, edge_m: float, ns: int, frame_id: str, rotation: np.ndarray | None = None
) -> MarkerArray:
    """One translucent CUBE per block: id = block id, pose = centre, scale = edge; ``rotation`` (3x3) turns
    the cubes (blocks are axis-aligned in the engine's world frame, which ``frame_id`` may be turned to)."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    _, _, _, qx, qy, qz, qw = (float(v) for v in pose_to_tum(T))
    out = MarkerArray()
    for i, c in enumerate(np.asarray(centres, dtype=np.float64).reshape(-1, 3)):
        m = Marker(header=header(ns, frame_id), ns="neb_blocks", id=i, type=Marker.CUBE, action=Marker.ADD)
        m.pose.position = Point(x=float(c[0]), y=float(c[1]), z=float(c[2]))
        m.pose.orientation = Quaternion(x=qx, y=qy, z=qz, w=qw)
        m.scale = Vector3(x=edge_m, y=edge_m, z=edge_m)
        m.color = ColorRGBA(r=0.2, g=0.6, b=1.0, a=0.15)
        out.markers.append(m)
    return out


def triangle_list(verts: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A TRIANGLE_LIST's ``points`` ``(3F, 3)`` float64 and ``colors`` ``(3F, 4)`` float32 (RGBA in 0..1,
    alpha 1) from a mesh part: vertices ``(V, 3)`` m, faces ``(F, 3)``, vertex colours ``(V, 3+)`` uint8.
    Both hold what ``Point(x, y, z)`` and ``ColorRGBA(r=c / 255.0, ...)`` hold, corner by corner."""
    corners = np.asarray(faces, dtype=np.int64).reshape(-1)
    points = np.asarray(verts, dtype=np.float64).reshape(-1, 3)[corners]
    colors = np.ones((len(corners), 4), dtype=np.float32)
    colors[:, :3] = np.asarray(colours)[corners, :3].astype(np.float64) / 255.0
    return points, colors


def mesh_marker_msgs(parts, ns: int, frame_id: str) -> MarkerArray:
    """The MarkerArray of :func:`neb_slam_ros.cdr.mesh_marker_array` as message objects, one Point and one
    ColorRGBA per corner (for a middleware that does not read the serialized form; slow on large meshes).

    ``parts``: block id -> ``(points, colors)`` of :func:`triangle_list`, or None for a DELETE marker.
    """
    out = MarkerArray()
    for block_id in sorted(parts):
        tri = parts[block_id]
        m = Marker(
            header=header(ns, frame_id),
            ns="neb_blocks",
            id=int(block_id),
            type=Marker.TRIANGLE_LIST,
            action=Marker.ADD if tri is not None else Marker.DELETE,
        )
        m.pose.orientation.w = 1.0
        m.scale = Vector3(x=1.0, y=1.0, z=1.0)
        m.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
        if tri is not None:
            points, colors = tri
            m.points = [Point(x=x, y=y, z=z) for x, y, z in np.asarray(points, dtype=np.float64).tolist()]
            m.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in np.asarray(colors, dtype=np.float64).tolist()]
        out.markers.append(m)
    return out


def point_cloud_msg(points: np.ndarray, rgb: np.ndarray, ns: int, frame_id: str) -> PointCloud2:
    """An unorganised PointCloud2 of ``(N, 3)`` points (metres) with colours ``(N, 3)`` uint8: fields x, y, z
    (float32) and rgb (the float32 whose bytes are 0x00RRGGBB, the layout RViz and PCL read), 16 bytes a
    point, little endian."""
    n = len(points)
    data = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    data["x"], data["y"], data["z"] = p[:, 0], p[:, 1], p[:, 2]
    c = np.asarray(rgb, dtype=np.uint32).reshape(-1, 3)
    data["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    fields = [
        PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, name in enumerate(("x", "y", "z", "rgb"))
    ]
    msg = PointCloud2(
        header=header(ns, frame_id),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * n,
        is_dense=True,
    )
    msg.data = data.tobytes()
    return msg


def occupancy_grid_msg(grid, ns: int, frame_id: str):
    """nav_msgs/OccupancyGrid of an :class:`~neb_slam_core.occupancy.OccupancySlice` (cells -1 unknown, 0 free,
    100 occupied; row = y): cell (0, 0)'s corner at the slice's origin and height in ``frame_id``, axes
    aligned with it."""
    from nav_msgs.msg import OccupancyGrid

    h, w = grid.cells.shape
    msg = OccupancyGrid(header=header(ns, frame_id))
    msg.info.map_load_time = to_time(ns)
    msg.info.resolution = float(grid.resolution_m)
    msg.info.width, msg.info.height = int(w), int(h)
    x0, y0 = grid.origin_xy
    msg.info.origin.position = Point(x=float(x0), y=float(y0), z=float(grid.height_m))
    msg.info.origin.orientation.w = 1.0
    msg.data = array.array("b", np.asarray(grid.cells, dtype=np.int8).tobytes())
    return msg
