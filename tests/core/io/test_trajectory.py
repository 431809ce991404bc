"""TUM trajectory files: exact stamps, the checks on every line, and ground truth that skips bad lines."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from neb_slam_core.errors import DatasetError
from neb_slam_core.io.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory

S = math.sqrt(0.5)
# hand-worked: (qx, qy, qz, qw) = (0, 0, sin 45, cos 45) is +90 degrees about z
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
GOOD = f"1305031102.175304 1.0 2.0 3.0 0 0 {S} {S}\n"


def write(tmp_path, text: str, name: str = "traj.txt"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_values_stamps_comments_and_separators(tmp_path):
    text = (
        "# timestamp tx ty tz qx qy qz qw\n"
        + GOOD
        + "\n"
        + "   # an indented comment\n"
        + "1305031102.2,-1.5,0.5,1e-3,0,0,0,1\r\n"  # commas, CRLF, an exponent
        + "-0.000000001 0 0 0 0 0 0 1.004\n"  # |q| within 1e-2 of 1: normalised
    )
    traj = read_tum_trajectory(write(tmp_path, text))
    np.testing.assert_array_equal(traj.stamps_ns, [1_305_031_102_175_304_000, 1_305_031_102_200_000_000, -1])
    np.testing.assert_allclose(traj.poses[0, :3, :3], RZ90, atol=1e-12)
    np.testing.assert_array_equal(traj.positions[0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(traj.positions[1], [-1.5, 0.5, 0.001])
    np.testing.assert_allclose(traj.poses[2, :3, :3], np.eye(3), atol=1e-12)


def test_round_trip_is_exact(tmp_path):
    stamps = np.array([0, 1, 1_305_031_102_175_304_123, 9_223_372_035_999_999_999], dtype=np.int64)
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, 3] = np.arange(12).reshape(4, 3) * 0.125
    path = tmp_path / "t.txt"
    write_tum_trajectory(path, Trajectory(stamps, poses))
    back = read_tum_trajectory(path)
    np.testing.assert_array_equal(back.stamps_ns, stamps)
    np.testing.assert_allclose(back.poses, poses, atol=1e-12)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1.0 1 2 3 0 0 1", r"line 3: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got 7"),
        ("1.0 1 2 3 0 0 0 1 5", r"line 3: expected 8 numbers .*, got 9"),
        ("1.0 1 2 x 0 0 0 1", r"line 3: not a number in '1.0 1 2 x 0 0 0 1'"),
        ("1.0 1 2 1-3 0 0 0 1", r"line 3: not a number"),
        ("1.0 1 2 1e 0 0 0 1", r"line 3: not a number"),
        ("1.0 1 2 3.0.1 0 0 0 1", r"line 3: not a number"),
        ("1e9 1 2 3 0 0 0 1", r"line 3: timestamp in '1e9 .*' is not a decimal number of seconds"),
        ("99999999999.0 1 2 3 0 0 0 1", r"line 3: timestamp .* within the int64 nanosecond range"),
        ("1.0 nan 2 3 0 0 0 1", r"line 3: pose is not finite in '1.0 nan 2 3 0 0 0 1'"),
        ("1.0 1 2 1e400 0 0 0 1", r"line 3: pose is not finite"),
        ("1.0 1 2 3 0 0 0 2", r"line 3: quaternion is not unit length \(\|q\| = 2.0000\)"),
    ],
)
def test_a_bad_line_is_an_error_naming_the_file_and_line(tmp_path, line, message):
    path = write(tmp_path, "# header\n" + GOOD + line + "\n" + GOOD.replace("1102.1", "1102.9"))
    with pytest.raises(DatasetError, match=message) as err:
        read_tum_trajectory(path)
    assert err.value.path == path


def test_ground_truth_skips_bad_lines_with_one_warning(tmp_path, caplog):
    text = (
        "# header\n"
        + GOOD  # line 2
        + "1305031102.2 nan 0 0 0 0 0 1\n"  # line 3: non-finite
        + "1305031102.3 0 0 0 0 0 0 1\n"  # line 4
        + "1305031102.4 0 0\n"  # line 5: cut short, as by a crash
        + "1305031102.5 0 0 0 0 0 0 0\n"  # line 6: zero quaternion
        + "1305031102.6 1 1 1 0 0 0 1\n"  # line 7
    )
    caplog.set_level(logging.WARNING)
    path = write(tmp_path, text, "groundtruth.txt")
    traj = read_tum_trajectory(path, skip_bad_lines=True)
    np.testing.assert_array_equal(
        traj.stamps_ns, [1_305_031_102_175_304_000, 1_305_031_102_300_000_000, 1_305_031_102_600_000_000]
    )
    np.testing.assert_array_equal(traj.positions[2], [1.0, 1.0, 1.0])
    (record,) = caplog.records
    text = record.getMessage()
    assert str(path) in text and "skipped 3 bad lines (3, 5, 6;" in text and "the other 3 poses" in text
    assert "line 3: pose is not finite" in text


def test_many_lines_are_checked_at_once(tmp_path, caplog):
    # ground-truth files have tens of thousands of lines; bad ones are listed up to 20, then counted
    n = 20_000
    stamps = 1_000_000_000 + np.arange(n, dtype=np.int64) * 10_000_000
    lines = [f"{s // 10**9}.{s % 10**9:09d} {k * 1e-3} 0 0 0 0 0 1" for k, s in enumerate(stamps)]
    bad = list(range(100, 2600, 100))  # 25 bad lines (0-based), non-finite
    for k in bad:
        lines[k] = lines[k].replace(" 0 0 0 0 0 1", " inf 0 0 0 0 1")
    caplog.set_level(logging.WARNING)
    traj = read_tum_trajectory(write(tmp_path, "\n".join(lines) + "\n"), skip_bad_lines=True)
    keep = np.setdiff1d(np.arange(n), bad)
    np.testing.assert_array_equal(traj.stamps_ns, stamps[keep])
    np.testing.assert_allclose(traj.positions[:, 0], keep * 1e-3)
    (record,) = caplog.records
    listed = ", ".join(str(k + 1) for k in bad[:20])
    assert f"skipped 25 bad lines ({listed} and 5 more;" in record.getMessage()


def test_empty_and_missing_files(tmp_path):
    assert len(read_tum_trajectory(write(tmp_path, ""))) == 0
    assert len(read_tum_trajectory(write(tmp_path, "# only a comment\n\n"))) == 0
    with pytest.raises(DatasetError, match="trajectory file not found"):
        read_tum_trajectory(tmp_path / "missing.txt")


def test_the_ground_truth_of_frames_keeps_those_with_a_pose_in_order():
    from neb_slam_core.types import Intrinsics, RgbdFrame

    intr = Intrinsics(10.0, 10.0, 2.0, 2.0, 4, 4)
    poses = [np.eye(4), None, np.diag([1.0, -1.0, -1.0, 1.0])]
    frames = [
        RgbdFrame(np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32), intr, 100 * (k + 1), T)
        for k, T in enumerate(poses)
    ]
    gt = Trajectory.of_frames(frames)
    assert gt.stamps_ns.tolist() == [100, 300]
    np.testing.assert_array_equal(gt.poses, np.stack([poses[0], poses[2]]))
    assert len(Trajectory.of_frames([])) == 0
