"""The loader registry and the helpers the loaders share."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.datasets import dataset_formats, loader_class, open_dataset
from neb_slam_core.datasets.base import associate, associate_unique, fps_stamp_ns, numbered_files
from neb_slam_core.errors import DatasetError


def test_all_formats_registered():
    formats = dataset_formats()
    assert formats == sorted(formats)
    assert {"apartment", "neural_rgbd", "replica", "scannet", "seven_scenes", "tum"} <= set(formats)
    assert loader_class("Replica").name == "replica"


def test_unknown_format():
    with pytest.raises(
        DatasetError, match="unknown dataset format 'kitti'; choose one of: apartment, .*replica"
    ) as err:
        loader_class("kitti")
    assert "seven_scenes" in str(err.value)


def test_open_missing_path(tmp_path):
    with pytest.raises(DatasetError, match="nope: no such file or directory"):
        open_dataset(tmp_path / "nope")


def test_open_unrecognised_layout(tmp_path):
    (tmp_path / "readme.txt").write_text("hello")
    with pytest.raises(DatasetError, match="cannot tell the dataset format from the layout"):
        open_dataset(tmp_path)


def test_layout_matching_two_formats(tmp_path):
    # rgb.txt + depth.txt (TUM) and results/ + traj.txt (Replica) in one folder
    for name in ("rgb.txt", "depth.txt", "traj.txt"):
        (tmp_path / name).write_text("")
    (tmp_path / "results").mkdir()
    with pytest.raises(DatasetError, match=r"matches several formats \(replica, tum\)"):
        open_dataset(tmp_path)


def test_numbered_files_sorts_by_number(tmp_path):
    for name in ("10.jpg", "9.jpg", "0.jpg", "notes.txt", "1.png"):
        (tmp_path / name).write_text("")
    files = numbered_files(tmp_path, r"(\d+)\.jpg", "colour images")
    assert list(files) == [0, 9, 10]
    assert files[10].name == "10.jpg"


def test_numbered_files_rejects_duplicate_numbers(tmp_path):
    (tmp_path / "7.jpg").write_text("")
    (tmp_path / "007.jpg").write_text("")
    with pytest.raises(DatasetError, match=r"colour images: frame number 7 is also used by"):
        numbered_files(tmp_path, r"(\d+)\.jpg", "colour images")


def test_fps_stamps():
    assert fps_stamp_ns(0, 30.0) == 0
    assert fps_stamp_ns(3, 30.0) == 100_000_000
    assert fps_stamp_ns(1, 30.0) == 33_333_333  # 33,333,333.3 rounds down
    assert fps_stamp_ns(2, 30.0) == 66_666_667  # 66,666,666.7 rounds up
    assert fps_stamp_ns(7, 15.0) == 466_666_667


def test_associate_nearest_within_window():
    ref = np.array([100, 50, 200])  # unsorted on purpose
    query = np.array([48, 90, 160, 400])
    # 48 -> 50 (index 1); 90 -> 100 (index 0); 160 is 40 from 200 and 60 from 100 -> 200 (index 2); 400 none
    np.testing.assert_array_equal(associate(query, ref, 45), [1, 0, 2, -1])


def test_associate_unique_uses_each_reference_once():
    ref = np.array([100])
    query = np.array([95, 103])
    np.testing.assert_array_equal(associate(query, ref, 10), [0, 0])
    # 103 is closer (3 vs 5): it takes the reference, 95 is left without
    np.testing.assert_array_equal(associate_unique(query, ref, 10), [-1, 0])
