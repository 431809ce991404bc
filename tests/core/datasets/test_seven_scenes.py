"""7-Scenes loader on tiny fake sequence and scene folders."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.seven_scenes import SevenScenesDataset
from neb_slam_core.errors import DatasetError
from neb_slam_core.types import Intrinsics

SMALL = Intrinsics(4.0, 4.0, 3.5, 2.5, 8, 6)


def make_seq(seq, fake, n=3, offset=0, skip_depth=(), ext="png"):
    """frame-%06d.{color.png,depth.png,pose.txt}; depth 1000 mm with pixel (0, 0) = 65535 (no reading)."""
    for k in range(n):
        stem = seq / f"frame-{k:06d}"
        fake.rgb(seq / f"frame-{k:06d}.color.{ext}", color=(10 + 20 * k, 0, 255))
        if k not in skip_depth:
            raw = np.full((fake.H, fake.W), 1000 * (k + 1), np.uint16)
            raw[0, 0] = 65535
            fake.depth(seq / f"frame-{k:06d}.depth.png", raw)
        stem.with_name(stem.name + ".pose.txt").write_text(fake.matrix_text(fake.pose(k + offset)))
    return seq


def test_frames_values_and_poses(tmp_path, fake):
    ds = SevenScenesDataset(make_seq(tmp_path / "seq-01", fake), intrinsics=SMALL)
    assert len(ds) == 3
    f = ds[1]
    np.testing.assert_array_equal(f.rgb, np.broadcast_to(np.array([30, 0, 255], np.uint8), (6, 8, 3)))
    assert f.depth_m[0, 0] == 0.0  # 65535 = no reading
    assert f.depth_m[5, 7] == 2.0  # 2000 mm
    np.testing.assert_array_equal(f.T_world_cam, fake.pose(1))
    assert f.stamp_ns == 33_333_333
    assert ds[-1].index == 2
    with pytest.raises(IndexError):
        ds[-4]


def test_default_intrinsics(tmp_path, fake):
    ds = SevenScenesDataset(make_seq(tmp_path / "seq-01", fake))
    assert ds.intrinsics == Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    with pytest.raises(DatasetError, match=r"frame-000000\.depth\.png: depth image is 8x6, expected 640x480"):
        ds[0]


def test_jpeg_colour(tmp_path, fake):
    ds = SevenScenesDataset(make_seq(tmp_path, fake, ext="jpg"), intrinsics=SMALL)
    assert np.abs(ds[2].rgb.astype(int) - [50, 0, 255]).max() <= 2


def test_scene_folder_picks_a_sequence(tmp_path, fake):
    make_seq(tmp_path / "seq-01", fake, n=2, offset=0)
    make_seq(tmp_path / "seq-02", fake, n=4, offset=10)
    first = SevenScenesDataset(tmp_path, intrinsics=SMALL)
    assert first.seq_dir.name == "seq-01" and len(first) == 2
    by_number = SevenScenesDataset(tmp_path, seq=2, intrinsics=SMALL)
    assert by_number.seq_dir.name == "seq-02" and len(by_number) == 4
    np.testing.assert_array_equal(by_number[0].T_world_cam, fake.pose(10))
    assert len(SevenScenesDataset(tmp_path, seq="seq-02", intrinsics=SMALL)) == 4
    with pytest.raises(DatasetError, match=r"seq-03: sequence folder not found; choose one of seq-01, seq-02"):
        SevenScenesDataset(tmp_path, seq=3, intrinsics=SMALL)


def test_detected_as_sequence_or_scene(tmp_path, fake):
    make_seq(tmp_path / "seq-01", fake)
    assert isinstance(open_dataset(tmp_path / "seq-01", intrinsics=SMALL), SevenScenesDataset)
    assert isinstance(open_dataset(tmp_path, intrinsics=SMALL), SevenScenesDataset)


def test_frames_without_depth_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    ds = SevenScenesDataset(make_seq(tmp_path, fake, n=5, skip_depth=(0, 2, 4)), intrinsics=SMALL)
    assert len(ds) == 2
    (w,) = skip_warnings()
    assert "skipped 3 of 5" in w.getMessage()
    assert ds[1].depth_m[1, 1] == 4.0
    np.testing.assert_array_equal(ds[1].T_world_cam, fake.pose(3))


def test_missing_pose(tmp_path, fake):
    make_seq(tmp_path, fake, n=3)
    (tmp_path / "frame-000001.pose.txt").unlink()
    with pytest.raises(
        DatasetError,
        match=r"2 pose files for 3 colour images.*no pose for frame-000001\.color\.png "
        r"\(expected frame-000001\.pose\.txt\)",
    ):
        SevenScenesDataset(tmp_path, intrinsics=SMALL)


def test_malformed_pose(tmp_path, fake):
    make_seq(tmp_path, fake, n=2)
    (tmp_path / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"frame-000001\.pose\.txt: camera-to-world pose \(4x4\): expected 16"):
        SevenScenesDataset(tmp_path, intrinsics=SMALL)


def test_non_rigid_pose(tmp_path, fake):
    make_seq(tmp_path, fake, n=2)
    bad = fake.pose(0)
    bad[:3, :3] *= 1.1
    (tmp_path / "frame-000000.pose.txt").write_text(fake.matrix_text(bad))
    with pytest.raises(DatasetError, match=r"frame-000000\.pose\.txt: camera-to-world pose: not a rigid transform"):
        SevenScenesDataset(tmp_path, intrinsics=SMALL)


def test_empty_folder(tmp_path):
    with pytest.raises(DatasetError, match="no colour images named frame-NNNNNN.color.png"):
        SevenScenesDataset(tmp_path, intrinsics=SMALL)
