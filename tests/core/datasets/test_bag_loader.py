"""The "bag" loader (neb_slam_core.datasets.bag): ROS 2 (sqlite3, mcap) and ROS 1 bags.

Round trips go through write_bag; the other bags are written by hand with rosbags' writers so the
loader is checked against messages built independently of our encoder.
"""

from __future__ import annotations

import hashlib
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from neb_slam_core.cli.main import main as cli_main
from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.bag import BagDataset
from neb_slam_core.datasets.base import Dataset
from neb_slam_core.datasets.tum import TumDataset
from neb_slam_core.errors import DatasetError, UnreadableFrameError
from neb_slam_core.geometry.se3 import make_pose, pose_to_tum
from neb_slam_core.io.bag import BagWriteOptions, write_bag
from neb_slam_core.types import Intrinsics, RgbdFrame

W, H = 8, 6
INTR = Intrinsics(7.5, 8.25, 3.5, 2.75, W, H)
T0 = 1_305_031_102_175_304_000
DT = 33_333_333
DIST = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
TS2 = get_typestore(Stores.ROS2_JAZZY)
TS1 = get_typestore(Stores.ROS1_NOETIC)
LOG = "neb_slam_core.datasets"


class Tiny(Dataset):
    """Five known frames; depth either whole millimetres (exact in 16UC1) or arbitrary float32 metres."""

    def __init__(self, mm_depth: bool = True, n: int = 5):
        self.root = Path("tiny")
        self.mm_depth, self.n = mm_depth, n

    def __len__(self) -> int:
        return self.n

    def _load(self, i: int) -> RgbdFrame:
        rng = np.random.default_rng(i)
        rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        if self.mm_depth:
            depth = rng.integers(0, 65536, (H, W)).astype(np.float32) / np.float32(1000.0)
        else:
            depth = rng.uniform(0.1, 9.0, (H, W)).astype(np.float32)
        depth[rng.random((H, W)) < 0.2] = 0.0  # invalid pixels
        pose = None if i == 3 else make_pose(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3))
        return RgbdFrame(rgb, depth, INTR, T0 + i * DT, pose, extras={"distortion": DIST})


def assert_same_frames(got: Dataset, want: Dataset, indices=None) -> None:
    assert len(got) == len(want)
    for i in range(len(want)) if indices is None else indices:
        g, w = got[i], want[i]
        assert g.index == i and g.stamp_ns == w.stamp_ns
        np.testing.assert_array_equal(g.rgb, w.rgb)
        assert g.depth_m.dtype == np.float32
        np.testing.assert_array_equal(g.depth_m, w.depth_m)
        assert g.intrinsics == w.intrinsics
        assert g.extras.get("distortion") == w.extras.get("distortion")
        if w.T_world_cam is None:
            assert g.T_world_cam is None
        else:
            np.testing.assert_allclose(g.T_world_cam, w.T_world_cam, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------------------------
# hand-written bags


def header(ts, stamp_ns: int, frame_id: str = "cam", ros1: bool = False):
    sec, ns = divmod(stamp_ns, 1_000_000_000)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns)
    Header = ts.types["std_msgs/msg/Header"]
    return Header(seq=0, stamp=stamp, frame_id=frame_id) if ros1 else Header(stamp=stamp, frame_id=frame_id)


def image(ts, stamp_ns, encoding, pixels: np.ndarray, ros1=False):
    h, w = pixels.shape[:2]
    data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
    return ts.types["sensor_msgs/msg/Image"](
        header=header(ts, stamp_ns, ros1=ros1),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=data.size // h,
        data=data,
    )


def camera_info(ts, stamp_ns, intr=INTR, ros1=False):
    K = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], dtype=np.float64)
    P = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    fields = dict(
        header=header(ts, stamp_ns, ros1=ros1),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob",
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
    arrays = dict(d=np.zeros(5), k=K, r=np.eye(3).reshape(-1), p=P)
    fields.update({k.upper() if ros1 else k: v for k, v in arrays.items()})
    return ts.types["sensor_msgs/msg/CameraInfo"](**fields)


def pose_stamped(ts, stamp_ns, T, ros1=False):
    t = ts.types
    tx, ty, tz, qx, qy, qz, qw = pose_to_tum(T)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    return t["geometry_msgs/msg/PoseStamped"](header=header(ts, stamp_ns, "world", ros1=ros1), pose=pose)


def write_ros2(path: Path, messages, storage="mcap", empty_topics=()):
    """``messages``: (topic, log_ns, msg) in any order; ``empty_topics``: (topic, msgtype) with no messages."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=8, storage_plugin=plugin) as writer:
        conns = {}
        for topic, msgtype in empty_topics:
            writer.add_connection(topic, msgtype, typestore=TS2)
        for topic, log_ns, msg in sorted(messages, key=lambda m: m[1]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=TS2)
            writer.write(conns[topic], log_ns, TS2.serialize_cdr(msg, msg.__msgtype__))
    return path


def rgb_of(i: int) -> np.ndarray:
    return np.random.default_rng(100 + i).integers(0, 256, (H, W, 3), dtype=np.uint8)


def simple_messages(
    n=3,
    rgb_topic="/camera/rgb/image",
    depth_topic="/camera/depth/image",
    info_topic="/camera/rgb/camera_info",
    colour_encoding="rgb8",
):
    msgs = []
    for i in range(n):
        t = T0 + i * DT
        msgs.append((info_topic, t, camera_info(TS2, t)))
        msgs.append((rgb_topic, t, image(TS2, t, colour_encoding, rgb_of(i))))
        msgs.append((depth_topic, t, image(TS2, t, "16UC1", np.full((H, W), 1000 + i, np.uint16))))
    return msgs


# ----------------------------------------------------------------------------------------------
# round trips through write_bag


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("depth_encoding", ["16UC1", "32FC1"])
def test_round_trip(tmp_path, storage, depth_encoding):
    src = Tiny(mm_depth=depth_encoding == "16UC1")
    write_bag(src, tmp_path / "b", BagWriteOptions(storage=storage, depth_encoding=depth_encoding), progress=False)
    ds = open_dataset(tmp_path / "b")  # format detected from the layout
    assert isinstance(ds, BagDataset) and ds.name == "bag" and ds.has_ground_truth
    assert_same_frames(ds, src)
    np.testing.assert_array_equal(ds.stamps_ns, T0 + np.arange(5) * DT)
    assert ds[-1].index == 4


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_single_storage_file_is_read(tmp_path, storage):
    src = Tiny()
    write_bag(src, tmp_path / "b", BagWriteOptions(storage=storage), progress=False)
    file = tmp_path / "b" / f"b.{'db3' if storage == 'sqlite3' else 'mcap'}"
    assert_same_frames(open_dataset(file, "bag"), src)


def test_pickled_dataset_reads_frames(tmp_path):
    write_bag(Tiny(), tmp_path / "b", progress=False)
    with BagDataset(tmp_path / "b") as ds:
        copy = pickle.loads(pickle.dumps(ds))
        assert_same_frames(copy, ds)
    copy.close()


# ----------------------------------------------------------------------------------------------
# other bags


@pytest.mark.parametrize("encoding", ["bgr8", "mono8", "rgba8", "bgra8"])
def test_colour_encodings_and_auto_picked_topics(tmp_path, encoding):
    rgb = rgb_of(0)
    pix = {
        "bgr8": rgb[..., ::-1],
        "rgba8": np.dstack([rgb, np.full((H, W), 9, np.uint8)]),
        "bgra8": np.dstack([rgb[..., ::-1], np.full((H, W), 9, np.uint8)]),
        "mono8": rgb[..., 1],
    }[encoding]
    t = T0
    # names the loader does not know: found by encoding; camera info found beside the colour topic
    bag = write_ros2(
        tmp_path / "b",
        [
            ("/cam/color/image_raw", t, image(TS2, t, encoding, pix)),
            ("/cam/aligned_depth/image_raw", t, image(TS2, t, "16UC1", np.full((H, W), 1500, np.uint16))),
            ("/cam/color/camera_info", t, camera_info(TS2, t)),
            ("/cam/aligned_depth/camera_info", t, camera_info(TS2, t, INTR.scaled(2 * W, 2 * H))),
        ],
    )
    ds = BagDataset(bag)
    assert (ds.topics.rgb, ds.topics.depth, ds.topics.camera_info) == (
        "/cam/color/image_raw",
        "/cam/aligned_depth/image_raw",
        "/cam/color/camera_info",
    )
    assert not ds.has_ground_truth
    f = ds[0]
    want = np.repeat(rgb[..., 1:2], 3, axis=2) if encoding == "mono8" else rgb
    np.testing.assert_array_equal(f.rgb, want)
    np.testing.assert_array_equal(f.depth_m, np.full((H, W), 1.5, np.float32))
    assert f.intrinsics == INTR and f.T_world_cam is None


def test_ros1_bag_with_tum_topic_names(tmp_path):
    """A ROS 1 bag laid out like TUM's downloads: 32FC1 depth with NaN holes, stamps != log times."""
    path = tmp_path / "tum.bag"
    poses = [make_pose(Rotation.from_rotvec([0.0, 0.1 * i, 0.0]).as_matrix(), [0.1 * i, 0.0, 1.0]) for i in range(3)]
    depth = [np.where(np.arange(H * W).reshape(H, W) % 5 == 0, np.nan, 0.5 + i).astype("<f4") for i in range(3)]
    with Writer1(path) as writer:
        c_rgb = writer.add_connection("/camera/rgb/image_color", "sensor_msgs/msg/Image", typestore=TS1)
        c_depth = writer.add_connection("/camera/depth/image", "sensor_msgs/msg/Image", typestore=TS1)
        c_info = writer.add_connection("/camera/rgb/camera_info", "sensor_msgs/msg/CameraInfo", typestore=TS1)
        c_gt = writer.add_connection("/mocap/pose", "geometry_msgs/msg/PoseStamped", typestore=TS1)
        c_other = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=TS1)  # ignored
        for i in range(3):
            t = T0 + i * DT
            ser = TS1.serialize_ros1
            writer.write(c_info, t + 4_000_000, ser(camera_info(TS1, t, ros1=True), "sensor_msgs/msg/CameraInfo"))
            writer.write(
                c_rgb, t + 5_000_000, ser(image(TS1, t, "rgb8", rgb_of(i), ros1=True), "sensor_msgs/msg/Image")
            )
            # depth 3 ms after colour, logged 7 ms late
            writer.write(
                c_depth,
                t + 10_000_000,
                ser(image(TS1, t + 3_000_000, "32FC1", depth[i], ros1=True), "sensor_msgs/msg/Image"),
            )
            writer.write(
                c_gt,
                t + 1_000_000,
                ser(pose_stamped(TS1, t + 1_000_000, poses[i], ros1=True), "geometry_msgs/msg/PoseStamped"),
            )
            writer.write(c_other, t, ser(TS1.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    ds = open_dataset(path)
    assert isinstance(ds, BagDataset)
    assert ds.topics.rgb == "/camera/rgb/image_color" and ds.topics.ground_truth == "/mocap/pose"
    assert len(ds) == 3
    for i, f in enumerate(ds):
        assert f.stamp_ns == T0 + i * DT + 3_000_000  # the depth header stamp, not the log time
        assert (f.extras["colour_stamp_ns"], f.extras["depth_stamp_ns"]) == (T0 + i * DT, f.stamp_ns)
        np.testing.assert_array_equal(f.rgb, rgb_of(i))
        np.testing.assert_array_equal(f.depth_m, np.nan_to_num(depth[i], nan=0.0))
        np.testing.assert_allclose(f.T_world_cam, poses[i], atol=1e-12)
        assert f.intrinsics == INTR
    colour = open_dataset(path, frame_stamp="colour")
    assert colour.stamps_ns.tolist() == [T0 + i * DT for i in range(3)]  # the colour header stamps
    np.testing.assert_allclose(colour[2].T_world_cam, poses[2], atol=1e-12)


def test_unpaired_frames_are_skipped_with_one_warning(tmp_path, caplog):
    msgs = [("/camera/rgb/camera_info", T0, camera_info(TS2, T0))]
    rgb_t = [T0 + k * DT for k in range(4)]
    depth_t = [rgb_t[0] + 5_000_000, rgb_t[1] - 19_000_000, rgb_t[3] + 50_000_000]  # only 2 within 20 ms
    msgs += [("/camera/rgb/image", t, image(TS2, t, "rgb8", rgb_of(k))) for k, t in enumerate(rgb_t)]
    msgs += [
        ("/camera/depth/image", t, image(TS2, t, "16UC1", np.full((H, W), k + 1, np.uint16)))
        for k, t in enumerate(depth_t)
    ]
    bag = write_ros2(tmp_path / "b", msgs)
    with caplog.at_level(logging.WARNING, logger=LOG):
        ds = BagDataset(bag)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "2 of 4" in warnings[0].getMessage()
    assert list(ds.stamps_ns) == depth_t[:2]  # their depth images' stamps
    assert ds[1].depth_m[0, 0] == np.float32(0.002)  # colour 1 paired with depth 1 (19 ms apart)
    # a wider window pairs colour 3 with the late depth image as well
    caplog.clear()
    assert len(BagDataset(bag, sync_slop_s=0.06)) == 3


def test_image_whose_data_does_not_decode_is_an_unreadable_frame(tmp_path):
    msgs = simple_messages(3)
    topic, t, good = msgs[5]  # frame 1's depth: keep the header and size, cut the pixels short
    assert topic == "/camera/depth/image"
    msgs[5] = (topic, t, type(good)(**{**good.__dict__, "data": good.data[:10]}))
    ds = BagDataset(write_ros2(tmp_path / "b", msgs))
    assert ds[0].stamp_ns == T0 and ds[2].stamp_ns == T0 + 2 * DT
    with pytest.raises(UnreadableFrameError, match=r"topic /camera/depth/image: 16UC1 image 8x6") as err:
        ds[1]
    assert err.value.index == 1 and err.value.path == tmp_path / "b"


def test_ground_truth_is_not_borrowed_by_a_frame_without_one(tmp_path):
    """Frames 10 ms apart; only the first has a pose: the second must get None, not its neighbour's."""
    msgs = simple_messages(1)
    t1 = T0 + 10_000_000
    msgs += [
        ("/camera/rgb/image", t1, image(TS2, t1, "rgb8", rgb_of(1))),
        ("/camera/depth/image", t1, image(TS2, t1, "16UC1", np.ones((H, W), np.uint16))),
        ("/ground_truth/pose", T0, pose_stamped(TS2, T0, np.eye(4))),
    ]
    ds = BagDataset(write_ros2(tmp_path / "b", msgs), sync_slop_s=0.004)
    assert len(ds) == 2
    np.testing.assert_array_equal(ds[0].T_world_cam, np.eye(4))
    assert ds[1].T_world_cam is None


def test_16uc1_depth_scale_option(tmp_path):
    ds = BagDataset(write_ros2(tmp_path / "b", simple_messages(2)), depth_scale=0.0002)  # TUM's 1/5000 m
    np.testing.assert_array_equal(ds[1].depth_m, np.full((H, W), np.float32(0.2002)))


# ----------------------------------------------------------------------------------------------
# bad input: errors name the bag and the topic


def test_missing_topic_is_named(tmp_path):
    bag = write_ros2(tmp_path / "b", simple_messages(1))
    with pytest.raises(DatasetError, match="/nope not found") as err:
        BagDataset(bag, rgb_topic="/nope")
    assert err.value.path == bag and "/camera/rgb/image" in str(err.value)  # lists what the bag has
    with pytest.raises(DatasetError, match="ground truth topic /camera/depth/image has type sensor_msgs/msg/Image"):
        BagDataset(bag, ground_truth_topic="/camera/depth/image")


def test_no_colour_topic_found(tmp_path):
    bag = write_ros2(
        tmp_path / "b",
        simple_messages(1, rgb_topic="/left/image", colour_encoding="rgb8")
        + [("/right/image", T0, image(TS2, T0, "bgr8", rgb_of(0)))],
    )
    with pytest.raises(DatasetError, match="2 Image topics have a colour encoding") as err:
        BagDataset(bag)
    assert "/left/image (rgb8)" in str(err.value) and "rgb_topic" in str(err.value)
    assert BagDataset(bag, rgb_topic="/right/image", camera_info_topic="/camera/rgb/camera_info")[0].rgb.shape == (
        H,
        W,
        3,
    )


def test_unknown_encoding_names_topic(tmp_path):
    bag = write_ros2(tmp_path / "b", simple_messages(1, colour_encoding="yuv422"))
    with pytest.raises(DatasetError, match=r"topic /camera/rgb/image: message 0 has encoding 'yuv422'") as err:
        BagDataset(bag)
    assert err.value.path == bag


def test_image_size_must_match_camera_info(tmp_path):
    msgs = [m for m in simple_messages(1) if m[0] != "/camera/depth/image"]
    msgs.append(("/camera/depth/image", T0, image(TS2, T0, "16UC1", np.ones((H, W + 2), np.uint16))))
    with pytest.raises(
        DatasetError,
        match=r"topic /camera/depth/image: message 0 is 10x6 but camera info on "
        r"/camera/rgb/camera_info says 8x6",
    ):
        BagDataset(write_ros2(tmp_path / "b", msgs))


def test_missing_camera_info(tmp_path):
    msgs = [m for m in simple_messages(1) if m[0] != "/camera/rgb/camera_info"]
    with pytest.raises(DatasetError, match="camera info topic /camera/rgb/camera_info not found"):
        BagDataset(write_ros2(tmp_path / "a", msgs))
    bag = write_ros2(tmp_path / "b", msgs, empty_topics=[("/camera/rgb/camera_info", "sensor_msgs/msg/CameraInfo")])
    with pytest.raises(DatasetError, match="camera info topic /camera/rgb/camera_info has no messages"):
        BagDataset(bag)


def test_explicit_intrinsics_replace_camera_info(tmp_path):
    msgs = [m for m in simple_messages(2) if m[0] != "/camera/rgb/camera_info"]
    bag = write_ros2(tmp_path / "b", msgs)
    better = Intrinsics(9.0, 9.5, 3.9, 3.1, W, H)
    ds = BagDataset(bag, intrinsics=better)
    assert ds[1].intrinsics == better and "distortion" not in ds[1].extras
    with pytest.raises(DatasetError, match="is 8x6 but the given intrinsics says 16x12"):
        BagDataset(bag, intrinsics=better.scaled(2 * W, 2 * H))


def test_not_a_bag(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(DatasetError, match="not a bag"):
        BagDataset(tmp_path / "x")
    (tmp_path / "broken.mcap").write_bytes(b"not an mcap file")
    with pytest.raises(DatasetError, match="cannot open bag") as err:
        BagDataset(tmp_path / "broken.mcap")
    assert err.value.path == tmp_path / "broken.mcap"


# ----------------------------------------------------------------------------------------------
# the real TUM excerpt


class Recording(Dataset):
    """Passes another dataset through, remembering a digest of every frame it hands out."""

    def __init__(self, inner: Dataset):
        self.inner, self.root = inner, inner.root
        self.seen: dict[int, tuple] = {}
        self.poses: dict[int, np.ndarray | None] = {}

    def __len__(self) -> int:
        return len(self.inner)

    def _load(self, i: int) -> RgbdFrame:
        f = self.inner[i]
        self.seen[i] = frame_digest(f)
        self.poses[i] = f.T_world_cam
        return f


def frame_digest(f: RgbdFrame) -> tuple:
    """Exact identity of the images (SHA-256 of their bytes) plus the small fields as they are."""
    return (
        hashlib.sha256(f.rgb.tobytes()).hexdigest(),
        f.rgb.shape,
        hashlib.sha256(f.depth_m.tobytes()).hexdigest(),
        f.depth_m.shape,
        f.depth_m.dtype,
        f.stamp_ns,
        f.intrinsics,
        f.extras.get("distortion"),
    )


def test_tum_conversion_reproduces_every_frame(tum_dir, tmp_path):
    """All 294 frames converted (mcap, 32FC1) and every one read back exactly as the TUM loader gave it.

    The frames are compared through digests taken while converting, so the TUM PNGs are decoded once.
    """
    tum = Recording(TumDataset(tum_dir))
    summary = write_bag(
        tum, tmp_path / "fr1_xyz", BagWriteOptions(storage="mcap", depth_encoding="32FC1"), progress=False
    )
    assert summary.n_frames == len(tum) == 294 and summary.n_poses == 292  # 2 frames have no GT within 0.02 s
    bag = BagDataset(tmp_path / "fr1_xyz")
    assert len(bag) == 294 and bag.has_ground_truth
    np.testing.assert_array_equal(bag.stamps_ns, tum.inner.stamps_ns)
    n_pose = 0
    for i, f in enumerate(bag):
        assert frame_digest(f) == tum.seen[i], f"frame {i} differs"
        want = tum.poses[i]
        if want is None:
            assert f.T_world_cam is None
        else:
            np.testing.assert_allclose(f.T_world_cam, want, rtol=0, atol=1e-9)
            n_pose += 1
    assert n_pose == 292


def test_cli_convert_tum_example(tum_dir, tmp_path, capsys):
    """The command of the module docstring, on the first frames."""
    assert cli_main(["convert", "tum", str(tum_dir), str(tmp_path / "fr1_xyz"), "--frames", "3"]) == 0
    out = capsys.readouterr().out
    assert "3 frames" in out and "/camera/depth/image" in out and "largest change" in out
    ds = open_dataset(tmp_path / "fr1_xyz")
    tum = TumDataset(tum_dir)
    assert len(ds) == 3 and ds[2].stamp_ns == tum[2].stamp_ns
    np.testing.assert_array_equal(ds[2].rgb, tum[2].rgb)
    # 16UC1 millimetres: TUM's 1/5000 m depth changes by at most half a millimetre
    assert np.abs(ds[2].depth_m - tum[2].depth_m).max() <= 0.0005 + 1e-6


def test_ground_truth_trajectory_is_the_frames_poses(tmp_path):
    """``BagDataset.ground_truth()`` gives, without reading images, the poses the frames carry."""
    from neb_slam_core.datasets.bag import BagDataset
    from neb_slam_core.io.bag import write_bag
    from neb_slam_core.synth.generate import generate

    ds_src = open_dataset(generate("small", tmp_path / "s", n_frames=4, progress=False))
    frames = [ds_src[i] for i in range(4)]
    write_bag(frames, tmp_path / "bag")
    with BagDataset(tmp_path / "bag") as ds:
        gt = ds.ground_truth()
        assert gt.stamps_ns.tolist() == [f.stamp_ns for f in frames]
        np.testing.assert_allclose(gt.poses, np.stack([f.T_world_cam for f in frames]), atol=1e-9)
