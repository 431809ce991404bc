"""Bag writing and the message <-> array conversions (neb_slam_core.io.bag).

Written bags are read back here with rosbags' own Reader (not our loader), so these tests check the
bag contents independently of neb_slam_core.datasets.bag.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from neb_slam_core.cli.main import main as cli_main
from neb_slam_core.datasets.base import Dataset
from neb_slam_core.errors import ConfigError, DatasetError
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.io.bag import (
    BagTopics,
    BagWriteOptions,
    camera_info_to_msg,
    decode_depth_m,
    decode_rgb,
    intrinsics_from_camera_info,
    pose_from_msg,
    pose_to_msg,
    quantise_depth,
    write_bag,
)
from neb_slam_core.types import Intrinsics, RgbdFrame

TS = get_typestore(Stores.ROS2_JAZZY)
W, H = 4, 3
INTR = Intrinsics(5.0, 6.0, 1.5, 1.0, W, H)
T0 = 1_700_000_000_123_456_789


def header(stamp_ns: int = T0, frame_id: str = "cam"):
    sec, ns = divmod(stamp_ns, 1_000_000_000)
    return TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame_id
    )


def image(encoding: str, data: bytes, width: int, height: int, step: int, bigendian: int = 0):
    return TS.types["sensor_msgs/msg/Image"](
        header=header(),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=bigendian,
        step=step,
        data=np.frombuffer(data, dtype=np.uint8).copy(),
    )


class Frames(Dataset):
    """``n`` frames of W x H: rgb = a known ramp, depth = whole millimetres, poses known (frame 1 has none)."""

    def __init__(self, n: int = 3, fail_at: int | None = None):
        self.root = Path("frames")
        self.n, self.fail_at = n, fail_at

    def __len__(self) -> int:
        return self.n

    def _load(self, i: int) -> RgbdFrame:
        if i == self.fail_at:
            raise DatasetError(self.root, f"frame {i} unreadable")
        rgb = ((np.arange(H * W * 3).reshape(H, W, 3) * 7 + 13 * i) % 256).astype(np.uint8)
        mm = (np.arange(H * W).reshape(H, W) * 250 + 100 * i).astype(np.uint16)
        mm[0, 0] = 0  # one invalid pixel
        depth = mm.astype(np.float32) / np.float32(1000.0)
        pose = None if i == 1 else make_pose(Rotation.from_rotvec([0.1 * i, -0.2, 0.3]).as_matrix(), [i, 2.0, -1.5])
        return RgbdFrame(
            rgb, depth, INTR, T0 + i * 33_333_333, pose, extras={"distortion": (0.1, -0.2, 0.003, 0.004, 0.5)}
        )


# ----------------------------------------------------------------------------------------------
# conversions


def test_quantise_depth_rounds_to_units_and_flags_out_of_range():
    depth = np.array([[0.0, 0.0016, 1.2344, np.nan], [-1.0, 70.0, 65.535, 0.0]], dtype=np.float32)
    units, max_err, n_far = quantise_depth(depth, 0.001)
    assert units.dtype == np.uint16
    np.testing.assert_array_equal(units, [[0, 2, 1234, 0], [0, 0, 65535, 0]])
    assert n_far == 1  # 70 m does not fit in 16 bits of millimetres
    assert max_err == pytest.approx(0.0004, abs=1e-6)  # 1.6 mm -> 2 mm and 1234.4 mm -> 1234 mm


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_decode_rgb_colour_encodings(encoding):
    rgb = np.arange(H * W * 3, dtype=np.uint8).reshape(H, W, 3) * 5
    pix = rgb[..., ::-1] if encoding.startswith("bgr") else rgb
    if encoding.endswith("a8"):
        pix = np.concatenate([pix, np.full((H, W, 1), 77, np.uint8)], axis=2)
    c = pix.shape[2]
    out = decode_rgb(image(encoding, pix.tobytes(), W, H, W * c))
    assert out.dtype == np.uint8 and out.shape == (H, W, 3)
    np.testing.assert_array_equal(out, rgb)


def test_decode_rgb_mono8_and_row_padding():
    gray = np.arange(H * W, dtype=np.uint8).reshape(H, W) * 9
    out = decode_rgb(image("mono8", gray.tobytes(), W, H, W))
    np.testing.assert_array_equal(out, np.repeat(gray[..., None], 3, axis=2))
    # rows padded to step = 3W + 2 bytes: padding must be dropped, not read as pixels
    rgb = np.arange(H * W * 3, dtype=np.uint8).reshape(H, W, 3)
    padded = np.concatenate([rgb.reshape(H, 3 * W), np.full((H, 2), 255, np.uint8)], axis=1)
    np.testing.assert_array_equal(decode_rgb(image("rgb8", padded.tobytes(), W, H, 3 * W + 2)), rgb)


def test_decode_rejects_unknown_encoding_and_short_data():
    with pytest.raises(ValueError, match="yuv422"):
        decode_rgb(image("yuv422", bytes(2 * W * H), W, H, 2 * W))
    with pytest.raises(ValueError, match="bytes"):
        decode_rgb(image("rgb8", bytes(3 * W * H - 1), W, H, 3 * W))
    with pytest.raises(ValueError, match="8UC3"):
        decode_depth_m(image("8UC3", bytes(3 * W * H), W, H, 3 * W))


def test_decode_depth_16uc1_scales_units():
    raw = np.array([[0, 1, 1500, 65535]] * H, dtype="<u2")[:, :W]
    out = decode_depth_m(image("16UC1", raw.tobytes(), W, H, 2 * W))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[0], np.array([0.0, 0.001, 1.5, 65.535], dtype=np.float32))
    # TUM's unit (1/5000 m), and the same values big-endian
    out = decode_depth_m(image("16UC1", raw.astype(">u2").tobytes(), W, H, 2 * W, bigendian=1), depth_scale=0.0002)
    np.testing.assert_array_equal(out[0], np.array([0.0, 0.0002, 0.3, 13.107], dtype=np.float32))


def test_decode_depth_32fc1_invalid_becomes_zero():
    raw = np.array([[1.25, np.nan, np.inf, -2.0]] * H, dtype="<f4")
    out = decode_depth_m(image("32FC1", raw.tobytes(), W, H, 4 * W))
    np.testing.assert_array_equal(out[0], np.array([1.25, 0.0, 0.0, 0.0], dtype=np.float32))


def test_camera_info_round_trip_through_cdr():
    d = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    msg = camera_info_to_msg(TS, INTR, T0, "cam", d)
    back = TS.deserialize_cdr(TS.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    assert back.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(back.k, [5.0, 0, 1.5, 0, 6.0, 1.0, 0, 0, 1])
    np.testing.assert_array_equal(back.p, [5.0, 0, 1.5, 0, 0, 6.0, 1.0, 0, 0, 0, 1, 0])
    np.testing.assert_array_equal(back.r, np.eye(3).reshape(-1))
    intr, dist = intrinsics_from_camera_info(back)
    assert intr == INTR and dist == d
    no_dist = camera_info_to_msg(TS, INTR, T0, "cam", None)
    assert no_dist.distortion_model == "plumb_bob" and list(no_dist.d) == [0.0] * 5


def test_pose_message_hand_worked_and_round_trip():
    # 90 degrees about z: quaternion (0, 0, sin 45, cos 45)
    T = make_pose(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [1.0, 2.0, 3.0])
    msg = pose_to_msg(TS, T, T0, "map")
    q = msg.pose.orientation
    assert (q.x, q.y) == (0.0, 0.0)
    assert q.z == pytest.approx(np.sqrt(0.5), abs=1e-15) and q.w == pytest.approx(np.sqrt(0.5), abs=1e-15)
    assert (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z) == (1.0, 2.0, 3.0)
    assert msg.header.frame_id == "map"
    np.testing.assert_allclose(pose_from_msg(msg), T, atol=1e-12)
    msg.pose.orientation.w = 3.0
    with pytest.raises(ValueError, match="unit length"):
        pose_from_msg(msg)


# ----------------------------------------------------------------------------------------------
# writing


def read_all(path: Path):
    """{topic: [(log_ns, msg)]} and the metadata version, read with rosbags only."""
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, log_ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append((log_ns, reader.deserialize(raw, conn.msgtype), conn.msgtype))
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_write_bag_contents(tmp_path, storage):
    frames = Frames(3)
    summary = write_bag(frames, tmp_path / "b", BagWriteOptions(storage=storage), progress=False)
    assert summary.n_frames == 3 and summary.n_poses == 2
    assert summary.size_bytes > 0 and summary.depth_max_error_m == 0.0  # whole millimetres survive 16UC1
    meta = (tmp_path / "b" / "metadata.yaml").read_text()
    assert "version: 8" in meta and f"storage_identifier: {storage}" in meta

    msgs = read_all(tmp_path / "b")
    t = BagTopics()
    assert {k: len(v) for k, v in msgs.items()} == {t.rgb: 3, t.depth: 3, t.camera_info: 3, t.ground_truth: 2}
    assert (
        msgs[t.rgb][0][2] == "sensor_msgs/msg/Image" and msgs[t.ground_truth][0][2] == "geometry_msgs/msg/PoseStamped"
    )
    for topic, items in msgs.items():
        for log_ns, msg, _ in items:
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            assert stamp == log_ns  # log time = header stamp = frame stamp
            assert msg.header.frame_id == ("map" if topic == t.ground_truth else "camera_rgb_optical_frame")
    for i, (log_ns, msg, _) in enumerate(msgs[t.depth]):
        f = frames[i]
        assert log_ns == f.stamp_ns
        assert (msg.encoding, msg.width, msg.height, msg.step, msg.is_bigendian) == ("16UC1", W, H, 2 * W, 0)
        np.testing.assert_array_equal(
            np.frombuffer(msg.data, "<u2").reshape(H, W), np.rint(f.depth_m.astype(np.float64) * 1000).astype(np.uint16)
        )
    rgb0 = msgs[t.rgb][0][1]
    assert (rgb0.encoding, rgb0.step) == ("rgb8", 3 * W)
    np.testing.assert_array_equal(rgb0.data.reshape(H, W, 3), frames[0].rgb)
    info = msgs[t.camera_info][2][1]
    assert (info.width, info.height, info.distortion_model) == (W, H, "plumb_bob")
    np.testing.assert_array_equal(info.d, [0.1, -0.2, 0.003, 0.004, 0.5])
    assert [m[0] for m in msgs[t.ground_truth]] == [frames[0].stamp_ns, frames[2].stamp_ns]  # frame 1 has no pose


def test_write_bag_32fc1_writes_nan_for_invalid(tmp_path):
    write_bag(Frames(1), tmp_path / "b", BagWriteOptions(depth_encoding="32FC1"), progress=False)
    msg = read_all(tmp_path / "b")[BagTopics().depth][0][1]
    depth = np.frombuffer(msg.data, "<f4").reshape(H, W)
    assert msg.encoding == "32FC1" and np.isnan(depth[0, 0])  # REP 118: no reading = NaN
    np.testing.assert_array_equal(depth.ravel()[1:], Frames(1)[0].depth_m.ravel()[1:])


def test_write_bag_custom_topics_and_max_frames(tmp_path):
    topics = BagTopics(rgb="/a/rgb", depth="/a/depth", camera_info="/a/info", ground_truth="/gt")
    summary = write_bag(Frames(3), tmp_path / "b", BagWriteOptions(topics=topics), max_frames=2, progress=False)
    assert summary.n_frames == 2
    assert {k: len(v) for k, v in read_all(tmp_path / "b").items()} == {
        "/a/rgb": 2,
        "/a/depth": 2,
        "/a/info": 2,
        "/gt": 1,
    }


def test_write_bag_refuses_to_overwrite(tmp_path):
    path = tmp_path / "b"
    write_bag(Frames(1), path, progress=False)
    with pytest.raises(DatasetError, match="overwrite") as err:
        write_bag(Frames(2), path, progress=False)
    assert err.value.path == path
    summary = write_bag(Frames(2), path, BagWriteOptions(overwrite=True, storage="sqlite3"), progress=False)
    assert summary.n_frames == 2 and len(read_all(path)[BagTopics().rgb]) == 2
    assert sorted(p.name for p in path.iterdir()) == ["b.db3", "metadata.yaml"]  # the old mcap is gone


def test_overwrite_never_deletes_a_folder_that_is_not_a_bag(tmp_path):
    folder = tmp_path / "precious"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me")
    with pytest.raises(DatasetError, match="not a ROS 2 bag"):
        write_bag(Frames(1), folder, BagWriteOptions(overwrite=True), progress=False)
    assert (folder / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious"]  # no staging folder left behind


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(DatasetError, match="frame 1 unreadable"):
        write_bag(Frames(3, fail_at=1), tmp_path / "b", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_write_options_are_checked():
    with pytest.raises(ConfigError, match="storage"):
        BagWriteOptions(storage="rosbag1")
    with pytest.raises(ConfigError, match="depth encoding"):
        BagWriteOptions(depth_encoding="16UC3")


def test_cli_convert_bag_to_bag(tmp_path, capsys):
    src, dst = tmp_path / "src", tmp_path / "dst"
    write_bag(Frames(3), src, progress=False)
    rc = cli_main(["convert", "bag", str(src), str(dst), "--storage", "sqlite3", "--depth", "32FC1", "--frames", "2"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "2 frames" in out and "/camera/rgb/image" in out and "/ground_truth/pose" in out and "size:" in out
    msgs = read_all(dst)
    assert len(msgs["/camera/depth/image"]) == 2 and msgs["/camera/depth/image"][0][1].encoding == "32FC1"
    assert (dst / "dst.db3").is_file()
    # again without --overwrite: a clear error, exit status 2, the bag untouched
    rc = cli_main(["convert", "auto", str(src), str(dst)])
    assert rc == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (dst / "dst.db3").is_file()


def test_cli_convert_rejects_bad_frame_count(tmp_path, capsys):
    src = tmp_path / "src"
    write_bag(Frames(1), src, progress=False)
    assert cli_main(["convert", "bag", str(src), str(tmp_path / "dst"), "--frames", "0"]) == 2
    assert "--frames" in capsys.readouterr().err


def test_out_of_range_depth_is_reported(tmp_path, caplog):
    class Far(Frames):
        def _load(self, i):
            f = super()._load(i)
            f.depth_m[1, 1] = 80.0
            return f

    with caplog.at_level(logging.WARNING, logger="neb_slam_core.io.bag"):
        summary = write_bag(Far(1), tmp_path / "b", progress=False)
    assert summary.n_depth_out_of_range == 1
    assert len([r for r in caplog.records if "16UC1 range" in r.getMessage()]) == 1
