"""ScanNet (NICE-SLAM export) loader on tiny fake folders."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.scannet import ScanNetDataset
from neb_slam_core.errors import DatasetError
from neb_slam_core.types import Intrinsics

# 4x4 intrinsic_depth.txt as ScanNet writes it (fx, fy, cx, cy in the upper-left 3x3)
K_TEXT = "5.5 0 3.75 0\n0 5.25 2.5 0\n0 0 1 0\n0 0 0 1\n"


def make_scannet(root, fake, n=3, lost=(), skip_depth=(), rgb_size=(16, 12)):
    """frames/{color,depth,pose,intrinsic}: colour 16x12 (resized to the 8x6 depth), depth k*1000+1000 mm."""
    frames = root / "frames"
    for k in range(n):
        fake.rgb(frames / "color" / f"{k}.jpg", color=(20 * k, 100, 200), size=rgb_size)
        if k not in skip_depth:
            fake.depth(frames / "depth" / f"{k}.png", 1000 + 1000 * k)
        T = np.full((4, 4), -np.inf) if k in lost else fake.pose(k)
        (frames / "pose").mkdir(parents=True, exist_ok=True)
        (frames / "pose" / f"{k}.txt").write_text(fake.matrix_text(T))
    (frames / "intrinsic").mkdir(parents=True, exist_ok=True)
    (frames / "intrinsic" / "intrinsic_depth.txt").write_text(K_TEXT)
    return root


def test_frames_values_and_poses(tmp_path, fake):
    ds = ScanNetDataset(make_scannet(tmp_path, fake))
    assert len(ds) == 3
    f = ds[2]
    assert f.intrinsics == Intrinsics(5.5, 5.25, 3.75, 2.5, 8, 6)  # size from the depth image
    assert f.rgb.shape == (6, 8, 3)  # 16x12 colour resized to the 8x6 depth
    assert np.abs(f.rgb.astype(int) - [40, 100, 200]).max() <= 2
    assert np.all(f.depth_m == 3.0)  # 3000 mm
    np.testing.assert_array_equal(f.T_world_cam, fake.pose(2))
    assert f.stamp_ns == 66_666_667
    assert ds[-3].index == 0
    with pytest.raises(IndexError):
        ds[3]


def test_colour_resized_with_area_interpolation(tmp_path, fake):
    make_scannet(tmp_path, fake, n=1)
    # 24x18 -> 8x6 is a 3x3 reduction. Only the centre of each 3x3 block is 90 (lossless PNG):
    # area averaging gives 90 / 9 = 10 everywhere; bilinear would give 90 (it samples the centres),
    # nearest 0 (it samples the corners).
    img = np.zeros((18, 24, 3), np.uint8)
    img[1::3, 1::3] = 90
    (tmp_path / "frames" / "color" / "0.jpg").unlink()
    fake.rgb_array(tmp_path / "frames" / "color" / "0.png", img)
    f = ScanNetDataset(tmp_path)[0]
    assert np.all(f.rgb == 10)


def test_numeric_order(tmp_path, fake):
    ds = ScanNetDataset(make_scannet(tmp_path, fake, n=12))
    # 0, 1, 2, ..., 9, 10, 11 (a name sort would give 0, 1, 10, 11, 2, ...)
    assert [f.rgb_path.name for f in ds.frames[:4]] == ["0.jpg", "1.jpg", "2.jpg", "3.jpg"]
    assert ds[10].depth_m[0, 0] == pytest.approx(11.0)
    np.testing.assert_array_equal(ds[11].T_world_cam, fake.pose(11))


def test_lost_poses_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    ds = ScanNetDataset(make_scannet(tmp_path, fake, n=5, lost=(1, 2)))
    assert len(ds) == 3
    (w,) = skip_warnings()
    assert "skipped 2 of 5" in w.getMessage() and "not finite" in w.getMessage()
    # frame 3 keeps its own depth, pose and stamp
    assert ds[1].depth_m[0, 0] == pytest.approx(4.0)
    np.testing.assert_array_equal(ds[1].T_world_cam, fake.pose(3))
    assert ds[1].stamp_ns == 100_000_000


def test_frames_without_depth_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    ds = ScanNetDataset(make_scannet(tmp_path, fake, n=4, skip_depth=(0, 2)))
    assert len(ds) == 2
    (w,) = skip_warnings()
    assert "skipped 2 of 4" in w.getMessage() and "no depth" in w.getMessage()


def test_detected_from_scene_or_frames_folder(tmp_path, fake):
    make_scannet(tmp_path, fake)
    assert isinstance(open_dataset(tmp_path), ScanNetDataset)
    ds = open_dataset(tmp_path / "frames")
    assert isinstance(ds, ScanNetDataset) and len(ds) == 3


def test_intrinsics_override(tmp_path, fake):
    override = Intrinsics(7.0, 7.0, 4.0, 3.0, 8, 6)
    ds = ScanNetDataset(make_scannet(tmp_path, fake), intrinsics=override)
    assert ds[0].intrinsics == override


def test_missing_intrinsics_file(tmp_path, fake):
    make_scannet(tmp_path, fake)
    (tmp_path / "frames" / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"intrinsic_depth\.txt: depth camera intrinsics .* not found"):
        ScanNetDataset(tmp_path)


def test_malformed_intrinsics_file(tmp_path, fake):
    make_scannet(tmp_path, fake)
    (tmp_path / "frames" / "intrinsic" / "intrinsic_depth.txt").write_text("5.5 0 3.75\n0 5.25 2.5\n0 0 1\n")
    with pytest.raises(DatasetError, match=r"intrinsic_depth\.txt: .*expected 16 numbers \(4x4\), got 9"):
        ScanNetDataset(tmp_path)


def test_missing_pose_file(tmp_path, fake):
    make_scannet(tmp_path, fake, n=4)
    (tmp_path / "frames" / "pose" / "2.txt").unlink()
    with pytest.raises(DatasetError, match=r"pose: 3 pose files for 4 colour images.*no pose for 2\.jpg"):
        ScanNetDataset(tmp_path)


def test_non_rigid_pose(tmp_path, fake):
    make_scannet(tmp_path, fake)
    bad = fake.pose(1)
    bad[3, 0] = 0.5
    (tmp_path / "frames" / "pose" / "1.txt").write_text(fake.matrix_text(bad))
    with pytest.raises(DatasetError, match=r"1\.txt: camera-to-world pose: not a rigid transform"):
        ScanNetDataset(tmp_path)


def test_missing_depth_folder(tmp_path, fake):
    make_scannet(tmp_path, fake)
    for p in (tmp_path / "frames" / "depth").iterdir():
        p.unlink()
    (tmp_path / "frames" / "depth").rmdir()
    with pytest.raises(DatasetError, match=r"depth: depth images .* folder not found"):
        ScanNetDataset(tmp_path)


def test_depth_of_wrong_size(tmp_path, fake):
    make_scannet(tmp_path, fake)
    fake.depth(tmp_path / "frames" / "depth" / "1.png", 1000, size=(4, 3))
    ds = ScanNetDataset(tmp_path)  # size comes from frame 0's depth image
    with pytest.raises(DatasetError, match=r"1\.png: depth image is 4x3, expected 8x6"):
        ds[1]
