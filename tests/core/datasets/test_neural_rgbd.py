"""NeuralRGBD loader on tiny fake folders, including the OpenGL -> OpenCV pose conversion."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.neural_rgbd import NeuralRgbdDataset
from neb_slam_core.errors import DatasetError
from neb_slam_core.types import Intrinsics

# Hand-worked pose: a camera rotated +90 degrees about world y, at (1, 2, 3), in OpenGL axes.
T_GL = np.array([[0.0, 0.0, 1.0, 1.0], [0.0, 1.0, 0.0, 2.0], [-1.0, 0.0, 0.0, 3.0], [0.0, 0.0, 0.0, 1.0]])
# OpenCV axes: y and z flipped, i.e. the second and third columns negated; translation unchanged.
T_CV = np.array([[0.0, 0.0, -1.0, 1.0], [0.0, -1.0, 0.0, 2.0], [-1.0, 0.0, 0.0, 3.0], [0.0, 0.0, 0.0, 1.0]])


def make_neural_rgbd(root, fake, n=3, poses=None, filtered=True, skip_depth=()):
    """images/imgK.png, depth_filtered/depthK.png (K*1000+500 mm) and depth/depthK.png (7000 mm), poses.txt,
    focal.txt."""
    for k in range(n):
        fake.rgb(root / "images" / f"img{k}.png", color=(30 * k, 60, 90))
        if k not in skip_depth:
            fake.depth(root / "depth" / f"depth{k}.png", 7000)
            if filtered:
                fake.depth(root / "depth_filtered" / f"depth{k}.png", 1000 * k + 500)
    poses = [T_GL] + [fake.pose(k) for k in range(1, n)] if poses is None else poses
    (root / "poses.txt").write_text("".join(fake.matrix_text(T) for T in poses))
    (root / "focal.txt").write_text("5.0\n")
    return root


def test_frames_values_intrinsics(tmp_path, fake):
    ds = NeuralRgbdDataset(make_neural_rgbd(tmp_path, fake))
    assert len(ds) == 3
    f = ds[2]
    np.testing.assert_array_equal(f.rgb, np.broadcast_to(np.array([60, 60, 90], np.uint8), (6, 8, 3)))
    assert np.all(f.depth_m == 2.5)  # depth_filtered preferred: 2500 mm
    # focal from focal.txt, principal point at the image centre (W/2, H/2)
    assert f.intrinsics == Intrinsics(5.0, 5.0, 4.0, 3.0, 8, 6)
    assert [ds[i].stamp_ns for i in (0, -1)] == [0, 66_666_667]
    with pytest.raises(IndexError):
        ds[-4]


def test_opengl_pose_converted_to_opencv(tmp_path, fake):
    ds = NeuralRgbdDataset(make_neural_rgbd(tmp_path, fake))
    T = ds[0].T_world_cam
    np.testing.assert_array_equal(T, T_CV)
    # meaning: the OpenCV optical axis (+z) looks where the OpenGL camera looks (-z): world -x here
    np.testing.assert_array_equal(T[:3, 2], -T_GL[:3, 2])
    np.testing.assert_array_equal(T[:3, 2], [-1.0, 0.0, 0.0])
    # image "up" in OpenGL (+y) is -y in OpenCV
    np.testing.assert_array_equal(T[:3, 1], -T_GL[:3, 1])
    # a generic pose: columns 1 and 2 negated, column 0 and translation kept
    expected = fake.pose(1) * np.array([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_array_equal(ds[1].T_world_cam, expected)


def test_plain_depth_folder_when_no_filtered(tmp_path, fake):
    ds = NeuralRgbdDataset(make_neural_rgbd(tmp_path, fake, filtered=False))
    assert np.all(ds[1].depth_m == 7.0)


def test_nan_poses_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    nan = np.full((4, 4), np.nan)
    poses = [T_GL, nan, fake.pose(2), nan, fake.pose(4)]
    ds = NeuralRgbdDataset(make_neural_rgbd(tmp_path, fake, n=5, poses=poses))
    assert len(ds) == 3
    (w,) = skip_warnings()
    assert "skipped 2 of 5" in w.getMessage() and "poses.txt" in w.getMessage()
    # survivors: images 0, 2, 4 with their own depth, stamp and pose
    assert ds[1].depth_m[0, 0] == pytest.approx(2.5)
    assert ds[2].stamp_ns == 133_333_333
    np.testing.assert_array_equal(ds[2].T_world_cam, fake.pose(4) * np.array([1.0, -1.0, -1.0, 1.0]))


def test_frames_without_depth_skipped_with_one_warning(tmp_path, fake, skip_warnings):
    ds = NeuralRgbdDataset(make_neural_rgbd(tmp_path, fake, n=4, skip_depth=(1, 2)))
    assert len(ds) == 2
    (w,) = skip_warnings()
    assert "skipped 2 of 4" in w.getMessage()


def test_detected(tmp_path, fake):
    assert isinstance(open_dataset(make_neural_rgbd(tmp_path, fake)), NeuralRgbdDataset)


def test_intrinsics_override(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake)
    (tmp_path / "focal.txt").unlink()  # not needed when intrinsics are given
    override = Intrinsics(6.0, 6.0, 3.5, 2.5, 8, 6)
    assert NeuralRgbdDataset(tmp_path, intrinsics=override)[0].intrinsics == override


def test_missing_focal(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake)
    (tmp_path / "focal.txt").unlink()
    with pytest.raises(DatasetError, match=r"focal\.txt: focal length .* not found"):
        NeuralRgbdDataset(tmp_path)


def test_pose_count_mismatch(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake, n=3, poses=[T_GL, T_GL])
    with pytest.raises(DatasetError, match=r"poses\.txt: 2 poses for 3 colour images"):
        NeuralRgbdDataset(tmp_path)


def test_poses_not_whole_matrices(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake, n=1)
    (tmp_path / "poses.txt").write_text(fake.matrix_text(T_GL) + "0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"poses\.txt: 5 rows is not a whole number of 4x4"):
        NeuralRgbdDataset(tmp_path)


def test_pose_row_of_wrong_length(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake, n=1)
    (tmp_path / "poses.txt").write_text("1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"poses\.txt: line 1: expected 4 numbers"):
        NeuralRgbdDataset(tmp_path)


def test_non_rigid_pose(tmp_path, fake):
    shear = np.eye(4)
    shear[0, 1] = 0.3
    make_neural_rgbd(tmp_path, fake, n=2, poses=[T_GL, shear])
    with pytest.raises(DatasetError, match=r"poses\.txt: pose of img1\.png: not a rigid transform"):
        NeuralRgbdDataset(tmp_path)


def test_missing_poses_file(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake)
    (tmp_path / "poses.txt").unlink()
    with pytest.raises(DatasetError, match=r"poses\.txt: pose file not found"):
        NeuralRgbdDataset(tmp_path)


def test_unreadable_depth(tmp_path, fake):
    make_neural_rgbd(tmp_path, fake)
    (tmp_path / "depth_filtered" / "depth1.png").write_bytes(b"\x89PNG broken")
    ds = NeuralRgbdDataset(tmp_path)
    with pytest.raises(DatasetError, match=r"depth1\.png: depth image missing or unreadable"):
        ds[1]
