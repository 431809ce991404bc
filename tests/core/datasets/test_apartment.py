"""NICE-SLAM Apartment (Azure Kinect, Open3D trajectory log) loader on tiny fake folders."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.apartment import ApartmentDataset
from neb_slam_core.errors import DatasetError
from neb_slam_core.types import Intrinsics

SMALL = Intrinsics(4.0, 4.0, 3.5, 2.5, 8, 6)


def log_text(fake, poses) -> str:
    """Open3D .log: per record 'k k+1 n' then the 4 rows."""
    return "".join(f"{k} {k + 1} {len(poses)}\n" + fake.matrix_text(T) for k, T in enumerate(poses))


def make_apartment(root, fake, n=3, poses=None, skip_depth=()):
    for k in range(n):
        fake.rgb(root / "color" / f"{k:05d}.jpg", color=(50 * k, 120, 30))
        if k not in skip_depth:
            fake.depth(root / "depth" / f"{k:05d}.png", 250 * (k + 1))
    poses = [fake.pose(k) for k in range(n)] if poses is None else poses
    (root / "scene").mkdir(parents=True, exist_ok=True)
    (root / "scene" / "trajectory.log").write_text(log_text(fake, poses))
    return root


def test_frames_values_and_poses(tmp_path, fake):
    ds = ApartmentDataset(make_apartment(tmp_path, fake), intrinsics=SMALL)
    assert len(ds) == 3
    f = ds[-1]
    assert f.index == 2
    assert np.abs(f.rgb.astype(int) - [100, 120, 30]).max() <= 2
    assert np.all(f.depth_m == 0.75)  # 750 mm
    np.testing.assert_array_equal(f.T_world_cam, fake.pose(2))
    assert f.stamp_ns == 66_666_667
    with pytest.raises(IndexError):
        ds[3]


def test_default_intrinsics_from_nice_slam_config(tmp_path, fake):
    ds = ApartmentDataset(make_apartment(tmp_path, fake))
    k = ds.intrinsics
    assert (k.width, k.height) == (1280, 720)
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx((607.4694, 607.4535, 636.9967, 369.2690), abs=1e-4)


def test_detected(tmp_path, fake):
    assert isinstance(open_dataset(make_apartment(tmp_path, fake), intrinsics=SMALL), ApartmentDataset)


def test_frames_without_depth_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    ds = ApartmentDataset(make_apartment(tmp_path, fake, n=4, skip_depth=(0, 3)), intrinsics=SMALL)
    assert len(ds) == 2
    (w,) = skip_warnings()
    assert "skipped 2 of 4" in w.getMessage()
    np.testing.assert_array_equal(ds[0].T_world_cam, fake.pose(1))


def test_pose_count_mismatch(tmp_path, fake):
    make_apartment(tmp_path, fake, n=3, poses=[fake.pose(0), fake.pose(1)])
    with pytest.raises(DatasetError, match=r"trajectory\.log: 2 poses for 3 colour images"):
        ApartmentDataset(tmp_path, intrinsics=SMALL)


def test_truncated_record(tmp_path, fake):
    make_apartment(tmp_path, fake, n=2)
    path = tmp_path / "scene" / "trajectory.log"
    path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")  # 9 lines
    with pytest.raises(DatasetError, match=r"trajectory\.log: 9 non-empty lines is not a whole number of 5-line"):
        ApartmentDataset(tmp_path, intrinsics=SMALL)


def test_bad_metadata_line(tmp_path, fake):
    make_apartment(tmp_path, fake, n=1)
    path = tmp_path / "scene" / "trajectory.log"
    path.write_text("0 1\n" + fake.matrix_text(fake.pose(0)))
    with pytest.raises(DatasetError, match=r"trajectory\.log: line 1: expected a metadata line of 3 numbers"):
        ApartmentDataset(tmp_path, intrinsics=SMALL)


def test_non_numeric_row(tmp_path, fake):
    make_apartment(tmp_path, fake, n=1)
    path = tmp_path / "scene" / "trajectory.log"
    path.write_text("0 0 1\n1 0 0 0\n0 1 0 x\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"trajectory\.log: lines 2-5: not numbers"):
        ApartmentDataset(tmp_path, intrinsics=SMALL)


def test_non_rigid_pose(tmp_path, fake):
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])  # orthonormal but det -1
    make_apartment(tmp_path, fake, n=2, poses=[fake.pose(0), reflection])
    with pytest.raises(DatasetError, match=r"trajectory\.log: pose at lines 7-10: not a rigid transform"):
        ApartmentDataset(tmp_path, intrinsics=SMALL)


def test_missing_trajectory(tmp_path, fake):
    make_apartment(tmp_path, fake)
    (tmp_path / "scene" / "trajectory.log").unlink()
    with pytest.raises(DatasetError, match=r"trajectory\.log: trajectory file not found"):
        ApartmentDataset(tmp_path, intrinsics=SMALL)


def test_depth_of_wrong_size(tmp_path, fake):
    make_apartment(tmp_path, fake)
    fake.depth(tmp_path / "depth" / "00001.png", 1000, size=(6, 8))
    ds = ApartmentDataset(tmp_path, intrinsics=SMALL)
    with pytest.raises(DatasetError, match=r"00001\.png: depth image is 6x8, expected 8x6"):
        ds[1]
