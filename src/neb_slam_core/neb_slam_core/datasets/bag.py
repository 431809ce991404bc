"""ROS bags: ROS 2 (sqlite3 or mcap; a bag directory or a single ``.db3`` / ``.mcap`` file) and ROS 1
``.bag`` files (the TUM benchmark's own downloads), read with ``rosbags.highlevel.AnyReader``.

Topics: the names :func:`neb_slam_core.io.bag.write_bag` writes, else the TUM ROS 1 names
(``/camera/rgb/image_color``, ``/camera/depth/image``, ``/camera/rgb/camera_info``), else, when the bag
has exactly one Image topic with a colour encoding and exactly one with a depth encoding, those; any of
them can be named explicitly. Ground truth comes from a geometry_msgs/PoseStamped topic when there is
one (``/tf`` is not read).

Colour (rgb8, bgr8, rgba8, bgra8, mono8) and depth (16UC1 / mono16 in units of ``depth_scale`` metres,
or 32FC1 metres) are paired by ``header.stamp``: nearest within ``sync_slop_s``, each image used once; a
frame takes the depth image's stamp (``frame_stamp``).
Intrinsics come from the first camera_info message (or an explicit ``intrinsics``, e.g. a calibration
better than the driver's); every image must have their size.

Reading is lazy: the constructor reads the bag once to index it (per image: connection, log time and
header stamp); ``dataset[i]`` then fetches just that frame's two messages by log time from a reader
kept open (and reopened after a fork, so a worker process gets its own).

Damaged ROS 2 bags (a recorder killed, a full disk): a storage file cut short, or a bag directory
without metadata.yaml, is read up to the damage by :mod:`neb_slam_core.io.bag_salvage` instead of
being refused, with one warning naming the file and what was lost. Any other damage is an error naming
the bag.
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError, UnreadableFrameError
from ..io.bag import (
    CAMERA_INFO_TYPE,
    COLOUR_ENCODINGS,
    DEPTH_DTYPES,
    IMAGE_TYPE,
    POSE_TYPE,
    BagTopics,
    decode_depth_m,
    decode_rgb,
    intrinsics_from_camera_info,
    pose_from_msg,
    stamp_ns_of,
)
from ..io.bag_salvage import STORAGE_SUFFIXES, salvage_bag
from ..types import COLOUR_STAMP, DEPTH_STAMP, Intrinsics, RgbdFrame
from .base import (
    Dataset,
    associate_unique,
    check_frame_stamp,
    check_intrinsics,
    frame_stamps,
    register,
    warn_skipped,
)

log = logging.getLogger(__name__)

#: topic names of the TUM RGB-D benchmark's ROS 1 bags
TUM_ROS1_TOPICS = BagTopics(
    rgb="/camera/rgb/image_color", depth="/camera/depth/image", camera_info="/camera/rgb/camera_info", ground_truth=""
)
BAG_SUFFIXES = (".mcap", ".db3", ".bag")
GT_MAX_DT_NS = 20_000_000  # 0.02 s


@dataclass
class _ImageIndex:
    """Where the messages of one image topic are, in bag order.

    Attributes:
        conn: ``(N,)`` index into the dataset's connection table.
        log_ns: ``(N,)`` int64 log time (what the reader seeks by).
        ordinal: ``(N,)`` position among messages of the same connection with the same log time.
        stamp_ns: ``(N,)`` int64 ``header.stamp``.
    """

    conn: np.ndarray
    log_ns: np.ndarray
    ordinal: np.ndarray
    stamp_ns: np.ndarray


def is_bag_path(path: Path) -> bool:
    """A ROS 2 bag directory (with metadata.yaml, or with the ``.mcap`` / ``.db3`` files of a recorder
    that never wrote it) or a ``.mcap`` / ``.db3`` / ``.bag`` file."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(p.suffix in STORAGE_SUFFIXES for p in path.iterdir())
    return path.is_file() and path.suffix in BAG_SUFFIXES


@register("bag")
class BagDataset(Dataset):
    """RGB-D frames from a ROS 1 or ROS 2 bag.

    Args:
        root: bag directory (ROS 2) or file (``.mcap``, ``.db3``, ``.bag``).
        rgb_topic, depth_topic, camera_info_topic: topic names; default: found as the module says.
        ground_truth_topic: PoseStamped topic with ``T_world_cam``; default ``/ground_truth/pose`` or the
            only PoseStamped topic; ``""`` to ignore ground truth.
        depth_scale: metres per unit of 16UC1 depth (0.001: millimetres).
        sync_slop_s: largest colour-depth stamp difference for a pair.
        intrinsics: use these instead of the camera_info topic (which then need not exist); the
            distortion still comes from camera_info when there is one.
        frame_stamp: ``"depth"`` or ``"colour"``: which image's ``header.stamp`` stamps a frame
            (:data:`~neb_slam_core.datasets.base.FRAME_STAMPS`) and picks its ground-truth pose.
    """

    def __init__(
        self,
        root: str | Path,
        rgb_topic: str | None = None,
        depth_topic: str | None = None,
        camera_info_topic: str | None = None,
        ground_truth_topic: str | None = None,
        depth_scale: float = 0.001,
        sync_slop_s: float = 0.02,
        intrinsics: Intrinsics | None = None,
        frame_stamp: str = "depth",
    ):
        self._reader = None
        self._reader_pid = -1
        self._salvaged = None  # the reader of a damaged bag (io.bag_salvage), kept across reopening
        self.root = Path(root)
        if not is_bag_path(self.root):
            raise DatasetError(
                self.root,
                f"not a bag: expected a ROS 2 bag directory with metadata.yaml, or a {', '.join(BAG_SUFFIXES)} file",
            )
        self.frame_stamp = check_frame_stamp(self.root, frame_stamp)
        if not depth_scale > 0:
            raise DatasetError(self.root, f"depth_scale must be > 0 metres per unit, got {depth_scale}")
        if not sync_slop_s >= 0:
            raise DatasetError(self.root, f"sync_slop_s must be >= 0, got {sync_slop_s}")
        self.depth_scale = float(depth_scale)
        self.sync_slop_s = float(sync_slop_s)
        self._intrinsics_override = intrinsics
        reader = self._open()
        try:
            self.topics = self._resolve_topics(
                reader, reader.topics, rgb_topic, depth_topic, camera_info_topic, ground_truth_topic
            )
            # connection table: the connections of the image topics, in a fixed order (rebuilt on reopen)
            self._conn_topics = [self.topics.rgb, self.topics.depth]
            self._conns = self._connection_table(reader)
            self._index(reader)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------------------------------
    # reader lifetime

    def _open(self):
        """The open reader of this bag (opened on first use and again in a forked process): rosbags'
        AnyReader, or for a damaged ROS 2 bag the salvaged part (module docstring)."""
        if self._reader is not None and self._reader_pid == os.getpid():
            return self._reader
        if self._salvaged is not None:  # indexed once; its files reopen on their own
            self._reader, self._reader_pid = self._salvaged, os.getpid()
            self._conns = self._connection_table(self._salvaged)
            return self._salvaged
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        is_ros1 = self.root.suffix == ".bag"
        store = get_typestore(Stores.ROS1_NOETIC if is_ros1 else Stores.ROS2_JAZZY)
        try:
            reader = AnyReader([self.root], default_typestore=store)
            reader.open()
        except Exception as exc:  # rosbags raises reader-, storage- and format-specific errors
            salvaged = None if is_ros1 else salvage_bag(self.root)
            if salvaged is None:
                raise DatasetError(self.root, f"cannot open bag: {type(exc).__name__}: {exc}") from None
            log.warning(
                "%s: rosbags cannot open it (%s: %s); reading it record by record up to the damage: %s",
                self.root,
                type(exc).__name__,
                exc,
                salvaged.report,
            )
            self._salvaged = reader = salvaged
        self._reader, self._reader_pid = reader, os.getpid()
        if getattr(self, "_conn_topics", None):
            self._conns = self._connection_table(reader)
        return reader

    def close(self) -> None:
        """Close the bag reader (reading a frame afterwards reopens it)."""
        if getattr(self, "_reader", None) is not None and self._reader_pid == os.getpid():
            with contextlib.suppress(Exception):  # closing is best effort
                self._reader.close()
        self._reader = None

    def __enter__(self) -> BagDataset:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_reader"], state["_reader_pid"], state["_conns"] = None, -1, []
        return state  # a salvaged reader travels with its index and without its open files

    def _connection_table(self, reader) -> list:
        topics = reader.topics
        return [c for t in self._conn_topics for c in topics[t].connections]

    # ------------------------------------------------------------------------------------------
    # topics

    def _first_encoding(self, reader, info) -> str | None:
        for conn, _, raw in reader.messages(connections=info.connections):
            return str(self._deserialize(reader, raw, conn).encoding)
        return None

    def _resolve_topics(self, reader, topics, rgb, depth, info, gt) -> BagTopics:
        default = BagTopics()
        image_topics = sorted(t for t, i in topics.items() if i.msgtype == IMAGE_TYPE)

        def require(topic: str, msgtype: str, role: str) -> str:
            if topic not in topics:
                have = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items())) or "none"
                raise DatasetError(self.root, f"{role} topic {topic} not found; the bag's topics: {have}")
            if topics[topic].msgtype != msgtype:
                raise DatasetError(
                    self.root, f"{role} topic {topic} has type {topics[topic].msgtype}, expected {msgtype}"
                )
            return topic

        def by_name(*names: str) -> str | None:
            return next((t for t in names if topics.get(t) and topics[t].msgtype == IMAGE_TYPE), None)

        if rgb is None:
            rgb = by_name(default.rgb, TUM_ROS1_TOPICS.rgb)
        if depth is None:
            depth = by_name(default.depth, TUM_ROS1_TOPICS.depth)
        if rgb is None or depth is None:
            encodings = {t: self._first_encoding(reader, topics[t]) for t in image_topics}
            colour = [t for t, e in encodings.items() if e in COLOUR_ENCODINGS]
            depthish = [t for t, e in encodings.items() if e in DEPTH_DTYPES]
            listing = ", ".join(f"{t} ({e})" for t, e in encodings.items()) or "none"
            if rgb is None:
                if len(colour) != 1:
                    raise DatasetError(
                        self.root,
                        f"colour topic {default.rgb} not found and {len(colour)} Image topics "
                        f"have a colour encoding (Image topics: {listing}); pass rgb_topic",
                    )
                rgb = colour[0]
            if depth is None:
                if len(depthish) != 1:
                    raise DatasetError(
                        self.root,
                        f"depth topic {default.depth} not found and {len(depthish)} Image topics "
                        f"have a depth encoding (Image topics: {listing}); pass depth_topic",
                    )
                depth = depthish[0]
        require(rgb, IMAGE_TYPE, "colour")
        require(depth, IMAGE_TYPE, "depth")
        if rgb == depth:
            raise DatasetError(self.root, f"colour and depth cannot both be topic {rgb}")

        if info is None:
            infos = sorted(t for t, i in topics.items() if i.msgtype == CAMERA_INFO_TYPE)
            sibling = rgb.rsplit("/", 1)[0] + "/camera_info"
            info = next((t for t in (default.camera_info, sibling) if t in infos), None)
            if info is None and len(infos) == 1:
                info = infos[0]
            if info is None and self._intrinsics_override is not None:
                info = ""  # not needed
            if info is None:
                raise DatasetError(
                    self.root,
                    f"camera info topic {default.camera_info} not found (nor {sibling}); "
                    f"CameraInfo topics: {', '.join(infos) or 'none'}; pass camera_info_topic",
                )
        if info:
            require(info, CAMERA_INFO_TYPE, "camera info")

        if gt is None:
            poses = sorted(t for t, i in topics.items() if i.msgtype == POSE_TYPE)
            gt = default.ground_truth if default.ground_truth in poses else (poses[0] if len(poses) == 1 else "")
        elif gt:
            require(gt, POSE_TYPE, "ground truth")
        return BagTopics(rgb=rgb, depth=depth, camera_info=info, ground_truth=gt)

    # ------------------------------------------------------------------------------------------
    # index

    def _deserialize(self, reader, raw, conn):
        try:
            return reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # rosbags raises several error types for corrupt data
            raise DatasetError(
                self.root, f"topic {conn.topic}: cannot decode a {conn.msgtype} message: {exc}"
            ) from None

    def _index(self, reader) -> None:
        t = self.topics
        topics = reader.topics
        slot = {c.id: k for k, c in enumerate(self._conns)}
        wanted = list(self._conns) + (list(topics[t.camera_info].connections) if t.camera_info else [])
        if t.ground_truth:
            wanted += list(topics[t.ground_truth].connections)
        streams = {t.rgb: ([], [], [], []), t.depth: ([], [], [], [])}  # conn, log, ordinal, stamp
        shapes = {t.rgb: [], t.depth: []}  # (width, height, encoding) per message
        seen: dict[tuple[int, int], int] = {}
        info_msg, gt_stamps, gt_poses = None, [], []
        try:
            messages = reader.messages(connections=wanted)
            for conn, log_ns, raw in messages:
                if conn.topic in streams:
                    msg = self._deserialize(reader, raw, conn)
                    k = slot[conn.id]
                    ordinal = seen.get((k, log_ns), 0)
                    seen[(k, log_ns)] = ordinal + 1
                    c, lg, o, s = streams[conn.topic]
                    c.append(k), lg.append(log_ns), o.append(ordinal), s.append(stamp_ns_of(msg))
                    shapes[conn.topic].append((int(msg.width), int(msg.height), str(msg.encoding)))
                elif conn.topic == t.camera_info:
                    if info_msg is None:
                        info_msg = self._deserialize(reader, raw, conn)
                else:
                    msg = self._deserialize(reader, raw, conn)
                    try:
                        gt_poses.append(pose_from_msg(msg))
                    except ValueError as exc:
                        raise DatasetError(
                            self.root, f"topic {t.ground_truth}: message {len(gt_poses)}: {exc}"
                        ) from None
                    gt_stamps.append(stamp_ns_of(msg))
        except DatasetError:
            raise
        except Exception as exc:  # corrupt storage surfaces as reader-specific errors
            raise DatasetError(self.root, f"cannot read bag messages: {exc}") from None

        self.distortion: tuple[float, ...] = ()
        if info_msg is None and self._intrinsics_override is None:
            raise DatasetError(self.root, f"camera info topic {t.camera_info} has no messages; intrinsics are needed")
        if info_msg is not None:
            try:
                self.intrinsics, self.distortion = intrinsics_from_camera_info(info_msg)
            except ValueError as exc:
                raise DatasetError(self.root, f"topic {t.camera_info}: {exc}") from None
        if self._intrinsics_override is not None:
            self.intrinsics = check_intrinsics(self._intrinsics_override, self.root)
        info_source = f"camera info on {t.camera_info}" if self._intrinsics_override is None else "the given intrinsics"
        size = (self.intrinsics.width, self.intrinsics.height)
        for topic, allowed in ((t.rgb, COLOUR_ENCODINGS), (t.depth, DEPTH_DTYPES)):
            if not shapes[topic]:
                raise DatasetError(self.root, f"topic {topic} has no messages")
            for j, (w, h, enc) in enumerate(shapes[topic]):
                if enc not in allowed:
                    raise DatasetError(
                        self.root,
                        f"topic {topic}: message {j} has encoding {enc!r}, expected one of {', '.join(allowed)}",
                    )
                if (w, h) != size:
                    raise DatasetError(
                        self.root, f"topic {topic}: message {j} is {w}x{h} but {info_source} says {size[0]}x{size[1]}"
                    )

        def as_index(cols) -> _ImageIndex:
            c, lg, o, s = cols
            return _ImageIndex(
                np.asarray(c, np.int64), np.asarray(lg, np.int64), np.asarray(o, np.int64), np.asarray(s, np.int64)
            )

        rgb_ix, depth_ix = as_index(streams[t.rgb]), as_index(streams[t.depth])
        pair = associate_unique(rgb_ix.stamp_ns, depth_ix.stamp_ns, int(round(self.sync_slop_s * 1e9)))
        keep = np.flatnonzero(pair >= 0)
        stamps = frame_stamps(rgb_ix.stamp_ns[keep], depth_ix.stamp_ns[pair[keep]], self.frame_stamp)
        order = np.argsort(stamps, kind="stable")
        keep, stamps = keep[order], stamps[order]
        n_rgb, n_depth = len(rgb_ix.stamp_ns), len(depth_ix.stamp_ns)
        unused_depth = n_depth - len(keep)
        why = (
            f"colour images on {t.rgb} with no depth on {t.depth} within {self.sync_slop_s} s "
            f"({unused_depth} of {n_depth} depth images unused)"
        )
        if len(keep) < n_rgb:
            warn_skipped(self.root, n_rgb - len(keep), n_rgb, why)
        elif unused_depth:
            log.warning(
                "%s: %d of %d depth images on %s have no colour image within %s s (unused)",
                self.root,
                unused_depth,
                n_depth,
                t.depth,
                self.sync_slop_s,
            )
        self._rgb_ix, self._depth_ix = rgb_ix, depth_ix
        self._rgb_rows, self._depth_rows = keep, pair[keep]
        self._stamps_ns = stamps

        # Each pose is used by at most one frame (the one nearest in time): a frame the bag gives no
        # pose must not borrow its neighbour's. Frames without one keep T_world_cam = None.
        self._poses: list[np.ndarray | None] | None = None
        if t.ground_truth:
            gi = associate_unique(self._stamps_ns, np.asarray(gt_stamps, np.int64), GT_MAX_DT_NS)
            n_missing = int((gi < 0).sum())
            if n_missing:
                log.warning(
                    "%s: %d of %d frames have no ground-truth pose on %s within 0.02 s (kept, without pose)",
                    self.root,
                    n_missing,
                    len(gi),
                    t.ground_truth,
                )
            self._poses = [gt_poses[j] if j >= 0 else None for j in gi]

    def ground_truth(self):
        """The ground-truth poses of the frames that have one, as a
        :class:`~neb_slam_core.io.trajectory.Trajectory` stamped with the frames' stamps (no image is read)."""
        from ..io.trajectory import Trajectory

        rows = [i for i, T in enumerate(self._poses or []) if T is not None]
        poses = np.stack([self._poses[i] for i in rows]) if rows else np.zeros((0, 4, 4))
        return Trajectory(self._stamps_ns[rows], poses)

    # ------------------------------------------------------------------------------------------
    # Dataset interface

    @classmethod
    def detect(cls, path: Path) -> bool:
        return is_bag_path(Path(path))

    @property
    def has_ground_truth(self) -> bool:
        return self._poses is not None

    @property
    def stamps_ns(self) -> np.ndarray:
        """``(N,)`` int64 stamps of the frames (``frame_stamp``'s image)."""
        return self._stamps_ns

    def __len__(self) -> int:
        return len(self._stamps_ns)

    def _read_pair(self, rgb_row: int, depth_row: int):
        """Deserialised (colour, depth) messages of one frame, fetched in one pass over the bag.

        One reader call covers both log times, so a storage chunk holding both is read once. Storage that
        fails to give them, or a message that does not decode, makes the frame unreadable
        (:class:`UnreadableFrameError`).
        """
        reader = self._open()
        wanted = [(self._rgb_ix, rgb_row), (self._depth_ix, depth_row)]
        keys = [(self._conns[int(ix.conn[r])].id, int(ix.log_ns[r]), int(ix.ordinal[r])) for ix, r in wanted]
        conns = list({id(c): c for c in (self._conns[int(ix.conn[r])] for ix, r in wanted)}.values())
        lo, hi = min(k[1] for k in keys), max(k[1] for k in keys)
        found: dict[tuple[int, int, int], tuple] = {}
        count: dict[tuple[int, int], int] = {}
        try:
            for conn, log_ns, raw in reader.messages(connections=conns, start=lo, stop=hi + 1):
                n = count.get((conn.id, log_ns), 0)
                count[(conn.id, log_ns)] = n + 1
                if (conn.id, log_ns, n) in keys:
                    found[(conn.id, log_ns, n)] = (conn, raw)
        except Exception as exc:  # reader-specific errors for corrupt storage
            raise UnreadableFrameError(self.root, f"cannot read messages between {lo} and {hi} ns: {exc}") from None
        out = []
        for key, (ix, r) in zip(keys, wanted):
            if key not in found:
                topic = self._conns[int(ix.conn[r])].topic
                raise UnreadableFrameError(
                    self.root, f"topic {topic}: message at {key[1]} ns vanished since the bag was indexed"
                )
            conn, raw = found[key]
            try:
                out.append(reader.deserialize(raw, conn.msgtype))
            except Exception as exc:  # rosbags raises several error types for corrupt data
                raise UnreadableFrameError(
                    self.root, f"topic {conn.topic}: the {conn.msgtype} message at {key[1]} ns does not decode: {exc}"
                ) from None
        return out[0], out[1]

    def _load(self, i: int) -> RgbdFrame:
        rgb_msg, depth_msg = self._read_pair(int(self._rgb_rows[i]), int(self._depth_rows[i]))
        rgb_topic, depth_topic = self.topics.rgb, self.topics.depth
        try:
            rgb = decode_rgb(rgb_msg)
        except ValueError as exc:
            raise UnreadableFrameError(self.root, f"topic {rgb_topic}: {exc}") from None
        try:
            depth = decode_depth_m(depth_msg, self.depth_scale)
        except ValueError as exc:
            raise UnreadableFrameError(self.root, f"topic {depth_topic}: {exc}") from None
        pose = None if self._poses is None or self._poses[i] is None else self._poses[i].copy()
        extras = {"distortion": self.distortion} if self.distortion else {}
        extras[COLOUR_STAMP] = int(self._rgb_ix.stamp_ns[self._rgb_rows[i]])
        extras[DEPTH_STAMP] = int(self._depth_ix.stamp_ns[self._depth_rows[i]])
        return RgbdFrame(rgb, depth, self.intrinsics, int(self._stamps_ns[i]), pose, extras=extras)
