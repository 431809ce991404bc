"""Replica (NICE-SLAM layout) loader on tiny fake folders."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.replica import ReplicaDataset
from neb_slam_core.errors import ConfigError, DatasetError
from neb_slam_core.types import Intrinsics

SMALL = Intrinsics(4.0, 4.0, 3.5, 2.5, 8, 6)


def make_replica(root, fake, n=3, depth_value=6553, skip_depth=(), poses=None):
    """results/frame%06d.jpg + depth%06d.png, traj.txt with fake.pose(k) per line."""
    for k in range(n):
        fake.rgb(root / "results" / f"frame{k:06d}.jpg", color=(40 * k, 100, 200))
        if k not in skip_depth:
            fake.depth(root / "results" / f"depth{k:06d}.png", depth_value + k)
    poses = [fake.pose(k) for k in range(n)] if poses is None else poses
    (root / "traj.txt").write_text("".join(" ".join(repr(float(v)) for v in T.ravel()) + "\n" for T in poses))
    return root


def test_frames_values_and_poses(tmp_path, fake):
    ds = ReplicaDataset(make_replica(tmp_path, fake), intrinsics=SMALL)
    assert len(ds) == 3
    f = ds[1]
    assert f.index == 1
    assert f.intrinsics == SMALL
    assert f.rgb.shape == (6, 8, 3) and f.rgb.dtype == np.uint8
    # a uniform colour survives JPEG within a grey level or two
    assert np.abs(f.rgb.astype(int) - [40, 100, 200]).max() <= 2
    assert f.depth_m.dtype == np.float32
    # PNG value 6554 / 6553.5 m
    assert np.allclose(f.depth_m, np.float32(6554) / np.float32(6553.5))
    assert ds[0].depth_m[0, 0] == pytest.approx(0.99992370, abs=1e-7)
    np.testing.assert_array_equal(f.T_world_cam, fake.pose(1))
    assert f.T_world_cam.dtype == np.float64
    # no stamps in the layout: frame n at n / 30 s
    assert [ds[i].stamp_ns for i in range(3)] == [0, 33_333_333, 66_666_667]
    np.testing.assert_array_equal(ds.stamps_ns, [0, 33_333_333, 66_666_667])


def test_indexing(tmp_path, fake):
    ds = ReplicaDataset(make_replica(tmp_path, fake), intrinsics=SMALL)
    assert ds[-1].index == 2
    np.testing.assert_array_equal(ds[-1].T_world_cam, fake.pose(2))
    with pytest.raises(IndexError):
        ds[3]
    with pytest.raises(IndexError):
        ds[-4]
    assert [f.index for f in ds[0:3:2]] == [0, 2]
    assert len(list(ds)) == 3


def test_fps_option(tmp_path, fake):
    ds = ReplicaDataset(make_replica(tmp_path, fake), intrinsics=SMALL, fps=10)
    assert ds[2].stamp_ns == 200_000_000
    with pytest.raises(ConfigError, match="fps"):
        ReplicaDataset(tmp_path, intrinsics=SMALL, fps=0)


def test_default_intrinsics_are_nice_slams(tmp_path, fake):
    ds = ReplicaDataset(make_replica(tmp_path, fake))
    assert ds.intrinsics == Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
    # the fake images are 8x6, not 1200x680: reading names the depth file and both sizes
    with pytest.raises(DatasetError, match=r"depth000000\.png.*8x6, expected 1200x680"):
        ds[0]


def test_detected(tmp_path, fake):
    ds = open_dataset(make_replica(tmp_path, fake), intrinsics=SMALL)
    assert isinstance(ds, ReplicaDataset) and ds.name == "replica"


def test_frames_without_depth_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    ds = ReplicaDataset(make_replica(tmp_path, fake, n=5, skip_depth=(1, 3)), intrinsics=SMALL)
    assert len(ds) == 3
    assert len(skip_warnings()) == 1
    assert "skipped 2 of 5" in skip_warnings()[0].getMessage()
    # the survivors keep their own pose (line k of traj.txt) and stamp (frame number / fps)
    np.testing.assert_array_equal(ds[1].T_world_cam, fake.pose(2))
    assert ds[1].stamp_ns == 66_666_667


def test_pose_count_mismatch(tmp_path, fake):
    make_replica(tmp_path, fake, n=3, poses=[fake.pose(0), fake.pose(1)])
    with pytest.raises(DatasetError, match=r"traj\.txt.*2 poses for 3 colour images"):
        ReplicaDataset(tmp_path, intrinsics=SMALL)


def test_non_rigid_pose(tmp_path, fake):
    bad = fake.pose(1)
    bad[:3, :3] *= 2.0
    make_replica(tmp_path, fake, n=3, poses=[fake.pose(0), bad, fake.pose(2)])
    with pytest.raises(DatasetError, match=r"traj\.txt: line 2: not a rigid transform"):
        ReplicaDataset(tmp_path, intrinsics=SMALL)


def test_traj_line_with_wrong_count(tmp_path, fake):
    make_replica(tmp_path, fake, n=2)
    lines = (tmp_path / "traj.txt").read_text().splitlines()
    (tmp_path / "traj.txt").write_text(lines[0] + "\n" + " ".join(lines[1].split()[:12]) + "\n")
    with pytest.raises(DatasetError, match=r"traj\.txt: line 2: expected 16 numbers.*got 12"):
        ReplicaDataset(tmp_path, intrinsics=SMALL)


def test_missing_traj(tmp_path, fake):
    make_replica(tmp_path, fake)
    (tmp_path / "traj.txt").unlink()
    with pytest.raises(DatasetError, match=r"traj\.txt: trajectory file not found"):
        ReplicaDataset(tmp_path, intrinsics=SMALL)


def test_missing_results_folder(tmp_path):
    (tmp_path / "traj.txt").write_text("")
    with pytest.raises(DatasetError, match="results: colour images .* folder not found"):
        ReplicaDataset(tmp_path, intrinsics=SMALL)


def test_unreadable_colour(tmp_path, fake):
    make_replica(tmp_path, fake)
    (tmp_path / "results" / "frame000001.jpg").write_bytes(b"not a jpeg")
    ds = ReplicaDataset(tmp_path, intrinsics=SMALL)
    with pytest.raises(DatasetError, match=r"frame000001\.jpg: colour image missing or unreadable"):
        ds[1]


def test_depth_of_wrong_dtype(tmp_path, fake):
    make_replica(tmp_path, fake)
    fake.depth(tmp_path / "results" / "depth000002.png", 200, dtype=np.uint8)
    ds = ReplicaDataset(tmp_path, intrinsics=SMALL)
    with pytest.raises(DatasetError, match=r"depth000002\.png: depth image must be 16-bit"):
        ds[2]


def test_colour_of_wrong_size(tmp_path, fake):
    make_replica(tmp_path, fake)
    fake.rgb(tmp_path / "results" / "frame000000.jpg", size=(10, 6))
    ds = ReplicaDataset(tmp_path, intrinsics=SMALL)
    with pytest.raises(DatasetError, match=r"frame000000\.jpg: colour image is 10x6, expected 8x6"):
        ds[0]
