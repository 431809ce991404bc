"""ROS bags of RGB-D frames: writing any dataset as a ROS 2 bag, and the message <-> array conversions.

Writing uses ``rosbags`` (pure Python, no ROS installation) with the ROS 2 Jazzy message definitions,
so a bag written here plays with ``ros2 bag play`` and feeds the node suite unchanged. Each frame
becomes four messages that share the frame's stamp as ``header.stamp`` and as the bag's log time:

- ``/camera/rgb/image``: sensor_msgs/Image, ``rgb8``;
- ``/camera/depth/image``: sensor_msgs/Image, ``16UC1`` millimetres (default) or ``32FC1`` metres with
  NaN where there is no reading (REP 118);
- ``/camera/rgb/camera_info``: sensor_msgs/CameraInfo, K, P = [K|0], size, ``plumb_bob`` distortion D
  (the frame's ``extras['distortion']``, else zeros);
- ``/ground_truth/pose``: geometry_msgs/PoseStamped, ``T_world_cam`` in frame ``map`` (frames with a
  known pose only).

Topic names are :class:`BagTopics` defaults; images and camera info use frame ``camera_rgb_optical_frame``.

The decoding helpers (:func:`decode_rgb`, :func:`decode_depth_m`, :func:`intrinsics_from_camera_info`,
:func:`pose_from_msg`) accept messages of either ROS version as deserialised by ``rosbags`` and raise
:class:`ValueError` with a message that the caller prefixes with the bag and topic.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import ConfigError, DatasetError
from ..geometry.se3 import pose_from_tum, pose_to_tum
from ..types import Intrinsics, RgbdFrame

log = logging.getLogger(__name__)

STORAGES = ("mcap", "sqlite3")
DEPTH_ENCODINGS = ("16UC1", "32FC1")

#: colour encodings we decode -> channels per pixel
COLOUR_ENCODINGS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
#: depth encodings we decode -> numpy dtype of one pixel (little endian; big-endian data is swapped)
DEPTH_DTYPES: dict[str, np.dtype] = {"16UC1": np.dtype("<u2"), "mono16": np.dtype("<u2"), "32FC1": np.dtype("<f4")}

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"

#: rosbag2 metadata version written: 8 is what ROS 2 Jazzy's rosbag2 writes (and every later one reads)
BAG_VERSION = 8


@dataclass(frozen=True)
class BagTopics:
    """Topic names of the camera streams and the ground truth in a bag."""

    rgb: str = "/camera/rgb/image"
    depth: str = "/camera/depth/image"
    camera_info: str = "/camera/rgb/camera_info"
    ground_truth: str = "/ground_truth/pose"


@dataclass(frozen=True)
class BagWriteOptions:
    """How :func:`write_bag` writes.

    Attributes:
        storage: ``'mcap'`` (ROS 2 Jazzy's default) or ``'sqlite3'``.
        depth_encoding: ``'16UC1'`` (integer units of ``depth_unit_m``) or ``'32FC1'`` (metres, exact).
        depth_unit_m: metres per 16UC1 unit; 0.001 (millimetres) is the ROS convention.
        topics: topic names.
        camera_frame_id: ``header.frame_id`` of images and camera info.
        world_frame_id: ``header.frame_id`` of the ground-truth poses.
        overwrite: replace an existing bag at the output path.
    """

    storage: str = "mcap"
    depth_encoding: str = "16UC1"
    depth_unit_m: float = 0.001
    topics: BagTopics = field(default_factory=BagTopics)
    camera_frame_id: str = "camera_rgb_optical_frame"
    world_frame_id: str = "map"
    overwrite: bool = False

    def __post_init__(self) -> None:
        if self.storage not in STORAGES:
            raise ConfigError(f"bag storage must be one of {', '.join(STORAGES)}, got {self.storage!r}")
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise ConfigError(
                f"bag depth encoding must be one of {', '.join(DEPTH_ENCODINGS)}, got {self.depth_encoding!r}"
            )
        if not self.depth_unit_m > 0:
            raise ConfigError(f"bag depth_unit_m must be > 0, got {self.depth_unit_m}")


@dataclass(frozen=True)
class TopicSummary:
    topic: str
    msgtype: str
    message_count: int


@dataclass(frozen=True)
class BagSummary:
    """What :func:`write_bag` wrote.

    Attributes:
        path: the bag directory.
        n_frames: frames written.
        n_poses: ground-truth poses written (frames without one get no pose message).
        topics: one entry per topic.
        size_bytes: total size of the bag's files.
        depth_max_error_m: largest depth change caused by 16UC1 quantisation (0 for 32FC1).
        n_depth_out_of_range: valid depth pixels beyond the 16UC1 range, written as 0 (invalid).
    """

    path: Path
    n_frames: int
    n_poses: int
    topics: tuple[TopicSummary, ...]
    size_bytes: int
    depth_max_error_m: float = 0.0
    n_depth_out_of_range: int = 0


# ----------------------------------------------------------------------------------------------
# encoding (frame -> messages)


def ros2_typestore():
    """The ROS 2 Jazzy message definitions (the distribution the node suite targets)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _header(typestore, stamp_ns: int, frame_id: str):
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def rgb_to_msg(typestore, rgb: np.ndarray, stamp_ns: int, frame_id: str):
    """``(H, W, 3)`` uint8 RGB -> sensor_msgs/Image ``rgb8``."""
    h, w = rgb.shape[:2]
    Image = typestore.types[IMAGE_TYPE]
    return Image(
        header=_header(typestore, stamp_ns, frame_id),
        height=h,
        width=w,
        encoding="rgb8",
        is_bigendian=0,
        step=3 * w,
        data=np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1),
    )


def quantise_depth(depth_m: np.ndarray, unit_m: float) -> tuple[np.ndarray, float, int]:
    """``(H, W)`` float32 metres -> ``(H, W)`` uint16 units of ``unit_m`` (0 stays invalid).

    Returns the image, the largest change a reader will see over valid pixels (metres; 0 when the
    input is whole units) and the number of valid pixels beyond the uint16 range (written as 0).
    """
    d = depth_m.astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    units = np.zeros(d.shape, dtype=np.float64)
    units[valid] = np.rint(d[valid] / unit_m)
    too_far = valid & (units > np.iinfo(np.uint16).max)
    units[too_far] = 0.0
    out = units.astype(np.uint16)
    ok = valid & ~too_far
    # the error a reader sees: float32 metres decoded from the units vs the float32 input
    decoded = (units[ok] * unit_m).astype(np.float32).astype(np.float64)
    max_err = float(np.abs(decoded - d[ok]).max()) if ok.any() else 0.0
    return out, max_err, int(too_far.sum())


def depth_to_msg(
    typestore, depth_m: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "16UC1", unit_m: float = 0.001
):
    """``(H, W)`` float32 metres -> (sensor_msgs/Image, max quantisation error m, pixels out of range).

    ``16UC1`` stores ``round(depth / unit_m)``; ``32FC1`` stores metres with NaN where invalid (REP 118).
    """
    h, w = depth_m.shape
    if encoding == "16UC1":
        raw, err, n_far = quantise_depth(depth_m, unit_m)
        step = 2 * w
    elif encoding == "32FC1":
        raw = depth_m.astype("<f4", copy=True)
        raw[~(np.isfinite(raw) & (raw > 0))] = np.nan
        err, n_far, step = 0.0, 0, 4 * w
    else:
        raise ValueError(f"depth encoding must be one of {', '.join(DEPTH_ENCODINGS)}, got {encoding!r}")
    Image = typestore.types[IMAGE_TYPE]
    msg = Image(
        header=_header(typestore, stamp_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.ascontiguousarray(raw).view(np.uint8).reshape(-1),
    )
    return msg, err, n_far


def camera_info_to_msg(
    typestore, intr: Intrinsics, stamp_ns: int, frame_id: str, distortion: Sequence[float] | None = None
):
    """Intrinsics -> sensor_msgs/CameraInfo (``plumb_bob``; D = ``distortion`` or zeros, R = I, P = [K|0])."""
    CameraInfo = typestore.types[CAMERA_INFO_TYPE]
    RegionOfInterest = typestore.types["sensor_msgs/msg/RegionOfInterest"]
    d = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64).reshape(-1)
    P = np.zeros((3, 4))
    P[:, :3] = intr.K
    return CameraInfo(
        header=_header(typestore, stamp_ns, frame_id),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob",
        d=d,
        k=intr.K.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def pose_to_msg(typestore, T_world_cam: np.ndarray, stamp_ns: int, frame_id: str):
    """``(4, 4)`` camera-to-world pose -> geometry_msgs/PoseStamped (quaternion with qw >= 0)."""
    ts = typestore.types
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in pose_to_tum(T_world_cam))
    pose = ts["geometry_msgs/msg/Pose"](
        position=ts["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz),
        orientation=ts["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    return ts[POSE_TYPE](header=_header(typestore, stamp_ns, frame_id), pose=pose)


# ----------------------------------------------------------------------------------------------
# decoding (messages -> arrays); works for ROS 1 and ROS 2 messages as rosbags deserialises them


def stamp_ns_of(msg) -> int:
    """``header.stamp`` of a message as integer nanoseconds."""
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _pixel_rows(msg, bytes_per_pixel: int) -> np.ndarray:
    """The image bytes as ``(H, W * bytes_per_pixel)`` uint8, dropping any row padding (``step``)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * bytes_per_pixel
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    if step < row:
        raise ValueError(f"{msg.encoding} image of width {w} needs step >= {row} bytes, got step {step}")
    if data.size < step * h:
        raise ValueError(f"{msg.encoding} image {w}x{h} with step {step} needs {step * h} bytes, got {data.size}")
    return data[: step * h].reshape(h, step)[:, :row]


def decode_rgb(msg) -> np.ndarray:
    """sensor_msgs/Image in rgb8, bgr8, rgba8, bgra8 or mono8 -> ``(H, W, 3)`` uint8 RGB (a new array)."""
    enc = msg.encoding
    if enc not in COLOUR_ENCODINGS:
        raise ValueError(f"colour encoding {enc!r} is not supported (expected one of {', '.join(COLOUR_ENCODINGS)})")
    c = COLOUR_ENCODINGS[enc]
    img = _pixel_rows(msg, c).reshape(int(msg.height), int(msg.width), c)
    if enc == "rgb8":
        return img.copy()
    code = {
        "bgr8": cv2.COLOR_BGR2RGB,
        "rgba8": cv2.COLOR_RGBA2RGB,
        "bgra8": cv2.COLOR_BGRA2RGB,
        "mono8": cv2.COLOR_GRAY2RGB,
    }[enc]
    return cv2.cvtColor(np.ascontiguousarray(img if c > 1 else img[..., 0]), code)


def decode_depth_m(msg, depth_scale: float = 0.001) -> np.ndarray:
    """sensor_msgs/Image 16UC1 / mono16 (units of ``depth_scale`` m) or 32FC1 (m) -> ``(H, W)`` float32 m.

    Invalid readings (0, NaN, +-Inf, negative) become 0.
    """
    enc = msg.encoding
    if enc not in DEPTH_DTYPES:
        raise ValueError(f"depth encoding {enc!r} is not supported (expected one of {', '.join(DEPTH_DTYPES)})")
    dtype = DEPTH_DTYPES[enc]
    if msg.is_bigendian:
        dtype = dtype.newbyteorder(">")
    h, w = int(msg.height), int(msg.width)
    raw = np.ascontiguousarray(_pixel_rows(msg, dtype.itemsize)).view(dtype).reshape(h, w)
    if dtype.kind == "u":
        # through float64 so that e.g. mm input gives exactly float32(mm / 1000)
        return (raw.astype(np.float64) * depth_scale).astype(np.float32)
    depth = raw.astype(np.float32)
    depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
    return depth


def _field(msg, lower: str):
    """CameraInfo fields are ``k``, ``d``, ... in ROS 2 and ``K``, ``D``, ... in ROS 1."""
    return getattr(msg, lower) if hasattr(msg, lower) else getattr(msg, lower.upper())


def intrinsics_from_camera_info(msg) -> tuple[Intrinsics, tuple[float, ...]]:
    """sensor_msgs/CameraInfo -> (intrinsics, distortion coefficients D)."""
    K = np.asarray(_field(msg, "k"), dtype=np.float64).reshape(-1)
    if K.size != 9 or not np.all(np.isfinite(K)):
        raise ValueError(f"camera info K must be 9 finite numbers, got {K.tolist()}")
    intr = Intrinsics(float(K[0]), float(K[4]), float(K[2]), float(K[5]), int(msg.width), int(msg.height))
    if not (intr.fx > 0 and intr.fy > 0 and intr.width > 0 and intr.height > 0):
        raise ValueError(f"camera info has no usable intrinsics (fx, fy, width, height must be > 0): {intr}")
    D = tuple(float(v) for v in np.asarray(_field(msg, "d"), dtype=np.float64).reshape(-1))
    return intr, D


def pose_from_msg(msg) -> np.ndarray:
    """geometry_msgs/PoseStamped -> ``(4, 4)`` float64 pose (quaternion normalised)."""
    p, q = msg.pose.position, msg.pose.orientation
    row = np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=np.float64)
    norm = float(np.linalg.norm(row[3:]))
    if not np.all(np.isfinite(row)) or abs(norm - 1.0) > 1e-2:
        raise ValueError(f"pose is not finite or its quaternion is not unit length (|q| = {norm:.4f})")
    row[3:] /= norm
    return pose_from_tum(row)


# ----------------------------------------------------------------------------------------------
# writing


def _bag_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _remove_existing(path: Path) -> None:
    """Delete an existing bag at ``path``; refuse anything that does not look like one."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file() and any(path.iterdir()):
            raise DatasetError(
                path, "exists and is not a ROS 2 bag (no metadata.yaml); not deleting it, choose another path"
            )
        shutil.rmtree(path)
    elif path.suffix in (".mcap", ".db3", ".bag"):
        path.unlink()
    else:
        raise DatasetError(path, "exists and is not a bag; not deleting it, choose another path")


def write_bag(
    frames: Sequence[RgbdFrame],
    path: str | Path,
    options: BagWriteOptions | None = None,
    max_frames: int | None = None,
    progress: bool = True,
) -> BagSummary:
    """Write ``frames`` (any :class:`~neb_slam_core.datasets.Dataset`) as a ROS 2 bag directory ``path``.

    The bag is built beside ``path`` and moved into place when complete, so an interrupted run never
    leaves a half-written bag (nor destroys the one it was to replace).

    Raises:
        DatasetError: ``path`` exists and ``options.overwrite`` is False, or a frame cannot be written.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    opts = options or BagWriteOptions()
    path = Path(path)
    if path.exists() and not opts.overwrite:
        raise DatasetError(path, "bag already exists; pass overwrite=True (--overwrite) to replace it")
    n = len(frames) if max_frames is None else min(len(frames), max(0, int(max_frames)))
    typestore = ros2_typestore()
    topics = opts.topics
    plugin = StoragePlugin.MCAP if opts.storage == "mcap" else StoragePlugin.SQLITE3

    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.parent / f".{path.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    tmp_bag = staging / path.name  # rosbags names the storage file after the directory
    n_poses, max_err, n_far = 0, 0.0, 0
    try:
        writer = Writer(tmp_bag, version=BAG_VERSION, storage_plugin=plugin)
        with writer:
            conn_rgb = writer.add_connection(topics.rgb, IMAGE_TYPE, typestore=typestore)
            conn_depth = writer.add_connection(topics.depth, IMAGE_TYPE, typestore=typestore)
            conn_info = writer.add_connection(topics.camera_info, CAMERA_INFO_TYPE, typestore=typestore)
            conn_pose = None
            ser = typestore.serialize_cdr
            for i in tqdm(range(n), desc=f"writing {path.name}", unit="frame", disable=not progress):
                frame = frames[i]
                stamp = int(frame.stamp_ns)
                if stamp < 0:
                    raise DatasetError(path, f"frame {i}: stamp {stamp} ns is negative; ROS time starts at 0")
                cam = opts.camera_frame_id
                info = camera_info_to_msg(typestore, frame.intrinsics, stamp, cam, frame.extras.get("distortion"))
                writer.write(conn_info, stamp, ser(info, CAMERA_INFO_TYPE))
                writer.write(conn_rgb, stamp, ser(rgb_to_msg(typestore, frame.rgb, stamp, cam), IMAGE_TYPE))
                depth_msg, err, far = depth_to_msg(
                    typestore, frame.depth_m, stamp, cam, opts.depth_encoding, opts.depth_unit_m
                )
                max_err, n_far = max(max_err, err), n_far + far
                writer.write(conn_depth, stamp, ser(depth_msg, IMAGE_TYPE))
                if frame.T_world_cam is not None:
                    if conn_pose is None:
                        conn_pose = writer.add_connection(topics.ground_truth, POSE_TYPE, typestore=typestore)
                    pose_msg = pose_to_msg(typestore, frame.T_world_cam, stamp, opts.world_frame_id)
                    writer.write(conn_pose, stamp, ser(pose_msg, POSE_TYPE))
                    n_poses += 1
        if path.exists():
            _remove_existing(path)
        tmp_bag.rename(path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)

    if n_far:
        log.warning(
            "%s: %d valid depth pixels beyond the 16UC1 range (%.1f m) were written as 0 (invalid)",
            path,
            n_far,
            np.iinfo(np.uint16).max * opts.depth_unit_m,
        )
    summary_topics = [
        TopicSummary(topics.rgb, IMAGE_TYPE, n),
        TopicSummary(topics.depth, IMAGE_TYPE, n),
        TopicSummary(topics.camera_info, CAMERA_INFO_TYPE, n),
    ]
    if n_poses:
        summary_topics.append(TopicSummary(topics.ground_truth, POSE_TYPE, n_poses))
    return BagSummary(
        path=path,
        n_frames=n,
        n_poses=n_poses,
        topics=tuple(summary_topics),
        size_bytes=_bag_size(path),
        depth_max_error_m=max_err,
        n_depth_out_of_range=n_far,
    )
