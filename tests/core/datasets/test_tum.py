"""TUM RGB-D loader: a hand-built fake folder, and the real fr1_xyz excerpt when it is present."""

from __future__ import annotations

import json
import logging
import math

import cv2
import numpy as np
import pytest

from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.base import FrameSkipper
from neb_slam_core.datasets.tum import TumDataset
from neb_slam_core.errors import DatasetError, UnreadableFrameError
from neb_slam_core.types import Intrinsics

S = math.sqrt(0.5)
# Hand-worked: the unit quaternion (qx, qy, qz, qw) = (0, 0, sin 45, cos 45) is +90 degrees about z.
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def make_tum(root, fake, size=(640, 480)):
    """Four colour frames and three depth frames with hand-chosen stamps (seconds):

    colour 1.000  1.033  1.050  1.100
    depth  1.005  1.040         1.095
    1.000-1.005 (5 ms) and 1.100-1.095 (5 ms) pair. 1.040 is within 0.02 s of both 1.033 (7 ms) and
    1.050 (10 ms); each depth is used once, so it goes to 1.033, and 1.050 has no other depth within
    0.02 s (the others are 45 ms away): it is skipped.
    Ground truth at 0.990 (frame 1.000, 10 ms), 1.035 (frame 1.033, 2 ms) and 1.200 (none within 0.02 s
    of 1.100, which keeps no pose).
    """
    rgb = [("1.000000", (10, 20, 30)), ("1.033000", (40, 50, 60)), ("1.050000", (70, 80, 90)), ("1.100000", (1, 2, 3))]
    depth = [("1.005000", 5000), ("1.040000", 10000), ("1.095000", 2500)]
    lines = ["# color images", "# timestamp filename"]
    for stamp, color in rgb:
        fake.rgb(root / "rgb" / f"{stamp}.png", color=color, size=size)
        lines.append(f"{stamp} rgb/{stamp}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    lines = ["# depth maps", "# timestamp filename"]
    for stamp, value in depth:
        fake.depth(root / "depth" / f"{stamp}.png", value, size=size)
        lines.append(f"{stamp} depth/{stamp}.png")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    (root / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        f"0.9900 1.0 2.0 3.0 0 0 {S} {S}\n"
        "1.0350 -1.0 0.5 0.0 0 0 0 1\n"
        "1.2000 9.0 9.0 9.0 0 0 0 1\n"
    )
    return root


@pytest.fixture
def fr2(tmp_path, fake):
    return make_tum(tmp_path / "rgbd_dataset_freiburg2_desk", fake)


def test_association_values_and_poses(fr2, fake, skip_warnings):
    ds = TumDataset(fr2)
    assert len(ds) == 3
    (w,) = skip_warnings()
    assert "skipped 1 of 4" in w.getMessage()
    # a frame takes its depth image's stamp; both images' stamps stay in extras
    assert [ds[i].stamp_ns for i in range(3)] == [1_005_000_000, 1_040_000_000, 1_095_000_000]
    np.testing.assert_array_equal(ds.stamps_ns, [1_005_000_000, 1_040_000_000, 1_095_000_000])
    assert [ds[i].extras["colour_stamp_ns"] for i in range(3)] == [1_000_000_000, 1_033_000_000, 1_100_000_000]
    assert [ds[i].extras["depth_stamp_ns"] for i in range(3)] == [1_005_000_000, 1_040_000_000, 1_095_000_000]
    # depth PNG / 5000: 5000 -> 1 m, 10000 -> 2 m, 2500 -> 0.5 m
    assert [float(ds[i].depth_m[3, 4]) for i in range(3)] == [1.0, 2.0, 0.5]
    assert ds[1].rgb[0, 0].tolist() == [40, 50, 60]
    assert ds[-1].rgb[0, 0].tolist() == [1, 2, 3]
    T0 = ds[0].T_world_cam
    np.testing.assert_allclose(T0[:3, :3], RZ90, atol=1e-12)
    np.testing.assert_array_equal(T0[:3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(ds[1].T_world_cam, [[1, 0, 0, -1.0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert ds[2].T_world_cam is None  # nearest ground truth is 0.1 s away
    assert ds.has_ground_truth
    with pytest.raises(IndexError):
        ds[3]


def test_colour_frame_stamps_pick_the_ground_truth_nearest_the_colour_image(tmp_path, fake):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg2_desk", fake)
    (root / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        "1.0000 1.0 0.0 0.0 0 0 0 1\n"
        "1.0060 2.0 0.0 0.0 0 0 0 1\n"
        "1.0320 3.0 0.0 0.0 0 0 0 1\n"
        "1.0410 4.0 0.0 0.0 0 0 0 1\n"
    )
    colour = TumDataset(root, frame_stamp="colour")
    assert colour.stamps_ns.tolist() == [1_000_000_000, 1_033_000_000, 1_100_000_000]
    # nearest ground truth to 1.000 is 1.000, to 1.033 is 1.032; 1.100 has none within 0.02 s
    assert [colour[i].T_world_cam[0, 3] for i in range(2)] == [1.0, 3.0] and colour[2].T_world_cam is None
    depth = TumDataset(root)
    assert depth.stamps_ns.tolist() == [1_005_000_000, 1_040_000_000, 1_095_000_000]
    # to 1.005 it is 1.006, to 1.040 it is 1.041
    assert [depth[i].T_world_cam[0, 3] for i in range(2)] == [2.0, 4.0] and depth[2].T_world_cam is None
    # the same images either way
    assert [colour[i].rgb[0, 0].tolist() for i in range(3)] == [depth[i].rgb[0, 0].tolist() for i in range(3)]


def test_frame_stamp_must_be_depth_or_colour(fr2):
    with pytest.raises(DatasetError, match="frame_stamp must be one of depth, colour, got 'rgb'"):
        TumDataset(fr2, frame_stamp="rgb")


def test_open_dataset_names_an_option_the_loader_lacks(fr2):
    assert open_dataset(fr2, frame_stamp="colour").frame_stamp == "colour"
    with pytest.raises(DatasetError, match="the tum loader has no option fps"):
        open_dataset(fr2, fps=30.0)


def test_intrinsics_from_folder_name(tmp_path, fr2, fake):
    k = TumDataset(fr2).intrinsics
    assert k == Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480)
    assert TumDataset(fr2)[0].extras["distortion"] == (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    fr3 = make_tum(tmp_path / "tum_fr3_x", fake)
    assert TumDataset(fr3).intrinsics == Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480)
    assert TumDataset(fr3, camera="fr1").intrinsics.fx == 517.3


def test_unknown_camera_lists_the_choices(tmp_path, fake):
    root = make_tum(tmp_path / "my_sequence", fake, size=(8, 6))
    with pytest.raises(DatasetError, match=r"my_sequence: cannot tell the TUM sensor.*fr1, fr2, fr3"):
        TumDataset(root)
    with pytest.raises(DatasetError, match=r"unknown TUM camera 'fr4'"):
        TumDataset(root, camera="fr4")
    small = Intrinsics(4.0, 4.0, 3.5, 2.5, 8, 6)
    assert TumDataset(root, intrinsics=small)[0].intrinsics == small


def test_intrinsics_json_takes_precedence(tmp_path, fake):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg1_small", fake, size=(8, 6))
    (root / "intrinsics.json").write_text(
        json.dumps({"fx": 4.5, "fy": 4.25, "cx": 3.5, "cy": 2.5, "width": 8, "height": 6})
    )
    ds = TumDataset(root)
    assert ds.intrinsics == Intrinsics(4.5, 4.25, 3.5, 2.5, 8, 6)
    assert ds[0].rgb.shape == (6, 8, 3)
    # an explicit argument still wins over the file
    override = Intrinsics(7.0, 7.0, 4.0, 3.0, 8, 6)
    assert TumDataset(root, intrinsics=override).intrinsics == override


def test_bad_intrinsics_json(tmp_path, fake):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg1_small", fake, size=(8, 6))
    (root / "intrinsics.json").write_text('{"fx": 4.5}')
    with pytest.raises(DatasetError, match=r"intrinsics\.json: expected a JSON object with fx"):
        TumDataset(root)


def test_detected(fr2):
    assert isinstance(open_dataset(fr2), TumDataset)
    assert isinstance(open_dataset(fr2, "tum"), TumDataset)


def test_missing_depth_index(fr2):
    (fr2 / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth\.txt: index file not found"):
        TumDataset(fr2)


def test_bad_index_line(fr2):
    (fr2 / "rgb.txt").write_text("1.0 rgb/1.000000.png\nabc rgb/x.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt: line 2: timestamp 'abc' is not a number"):
        TumDataset(fr2)


def test_bad_groundtruth_lines_are_skipped_with_one_warning(fr2, caplog):
    (fr2 / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        "0.9900 nan 2.0 3.0 0 0 0 1\n"  # line 2: frame 1.000's pose, not finite
        "1.0350 -1.0 0.5 0.0 0 0 0 1\n"
        "1.0400 1.0 2.0\n"  # line 4: cut short
        "1.1000 0 0 0 0 0 0 2\n"  # line 5: frame 1.100's pose, quaternion not unit length
    )
    caplog.set_level(logging.WARNING)
    ds = TumDataset(fr2)
    assert ds.has_ground_truth
    assert ds[0].T_world_cam is None and ds[2].T_world_cam is None  # their lines were skipped
    np.testing.assert_array_equal(ds[1].T_world_cam[:3, 3], [-1.0, 0.5, 0.0])
    warnings = [r.getMessage() for r in caplog.records if "bad line" in r.getMessage()]
    assert len(warnings) == 1 and "groundtruth.txt: skipped 3 bad lines (2, 4, 5;" in warnings[0]


def test_colour_of_wrong_size(fr2, fake):
    fake.rgb(fr2 / "rgb" / "1.033000.png", size=(320, 240))
    with pytest.raises(DatasetError, match=r"1\.033000\.png: colour image is 320x240, expected 640x480") as err:
        TumDataset(fr2)[1]
    assert not isinstance(err.value, UnreadableFrameError)  # a wrong image is not skipped as damage


def test_truncated_or_missing_image_is_an_unreadable_frame_that_a_skipper_skips(fr2, caplog, capfd):
    depth = fr2 / "depth" / "1.040000.png"  # frame 1's depth
    data = depth.read_bytes()
    assert len(data) > 100
    depth.write_bytes(data[:100])
    (fr2 / "rgb" / "1.100000.png").unlink()  # frame 2's colour
    ds = TumDataset(fr2)
    with pytest.raises(UnreadableFrameError, match=r"1\.040000\.png: depth image missing or unreadable") as err:
        ds[1]
    assert err.value.index == 1 and err.value.path == depth
    caplog.set_level(logging.WARNING)
    caplog.clear()
    skipper = FrameSkipper(ds)
    assert [skipper.read(i) is None for i in range(len(ds))] == [False, True, True]
    assert len(skipper) == 2 and not caplog.records  # nothing logged per frame
    assert capfd.readouterr().err == ""  # nor printed by OpenCV
    skipper.warn()
    (record,) = caplog.records
    text = record.getMessage()
    assert "skipped 2 frames whose colour or depth could not be read" in text
    assert f"frame 1: {depth}: depth image" in text and f"frame 2: {fr2 / 'rgb' / '1.100000.png'}: colour" in text


def test_no_groundtruth_file(fr2):
    (fr2 / "groundtruth.txt").unlink()
    ds = TumDataset(fr2)
    assert not ds.has_ground_truth and ds[0].T_world_cam is None


# ------------------------------------------------------------------------------------------------
# the real 300-frame excerpt of fr1_xyz


def _read_groundtruth(path):
    """Independent parse: (stamps in s as float64, rows tx ty tz qx qy qz qw)."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return np.array([float(r[0]) for r in rows]), np.array([[float(v) for v in r[1:]] for r in rows])


def _quat_to_matrix(qx, qy, qz, qw):
    """Closed-form rotation matrix of a unit Hamilton quaternion."""
    return np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )


def test_real_fr1_xyz(tum_dir, skip_warnings):
    ds = open_dataset(tum_dir, frame_stamp="colour")
    assert isinstance(ds, TumDataset)
    # 300 colour frames, 6 of them without a depth frame within 0.02 s
    assert len(ds) == 294
    skipped = skip_warnings()
    assert len(skipped) == 1 and "skipped 6 of 300" in skipped[0].getMessage()
    assert ds.intrinsics == Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)

    f0 = ds[0]
    first_rgb = next(
        line.split()
        for line in (tum_dir / "rgb.txt").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    )
    assert first_rgb[0] == "1305031102.175304"
    assert f0.stamp_ns == 1_305_031_102_175_304_000

    gt_s, gt_rows = _read_groundtruth(tum_dir / "groundtruth.txt")
    j = int(np.argmin(np.abs(gt_s - 1305031102.175304)))
    assert abs(gt_s[j] - 1305031102.175304) <= 0.02
    tx, ty, tz, qx, qy, qz, qw = gt_rows[j]
    q = np.array([qx, qy, qz, qw]) / np.linalg.norm([qx, qy, qz, qw])
    np.testing.assert_allclose(f0.T_world_cam[:3, :3], _quat_to_matrix(*q), atol=1e-12)
    np.testing.assert_array_equal(f0.T_world_cam[:3, 3], [tx, ty, tz])
    np.testing.assert_array_equal(f0.T_world_cam[3], [0, 0, 0, 1])

    # depth = PNG value / 5000, exactly, at a pixel with a reading
    # its depth partner: the nearest depth.txt stamp (within 0.02 s)
    depth_rows = [
        line.split()
        for line in (tum_dir / "depth.txt").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    d_s = np.array([float(r[0]) for r in depth_rows])
    partner = depth_rows[int(np.argmin(np.abs(d_s - 1305031102.175304)))][1]
    raw = cv2.imread(str(tum_dir / partner), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    y, x = 240, 320
    assert raw[y, x] > 0
    assert f0.depth_m[y, x] == np.float32(raw[y, x]) / np.float32(5000.0)
    # by default the frame is stamped with that depth image's time
    depth_stamp = depth_rows[int(np.argmin(np.abs(d_s - 1305031102.175304)))][0]
    assert depth_stamp == "1305031102.160407"  # 15 ms before the colour image
    assert open_dataset(tum_dir)[0].stamp_ns == 1_305_031_102_160_407_000
    assert np.array_equal(f0.depth_m == 0, raw == 0)
    assert f0.rgb.shape == (480, 640, 3)

    # frames with no motion-capture sample within 0.02 s stay, without a pose
    for i in (195, 196):
        t = ds.stamps_ns[i] * 1e-9
        assert np.min(np.abs(gt_s - t)) > 0.02
        assert ds[i].T_world_cam is None
    t = ds.stamps_ns[194] * 1e-9
    assert np.min(np.abs(gt_s - t)) <= 0.02 and ds[194].T_world_cam is not None
