"""A bad parameter stops a node at start with exit status 2 and one line naming the parameter and what
was wrong with it (here: the mapper's and slam's ``map_file``, and a range check)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros]

REPO = Path(__file__).resolve().parents[2]


def _start(node: str, env: dict[str, str], *params: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", f"neb_slam_ros.{node}", "--ros-args", "-p", "config:=ci"]
    for p in params:
        cmd += ["-p", p]
    return subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("node", ["mapper", "slam"])
def test_a_map_file_that_cannot_be_continued_stops_the_node_naming_it(node, ros_env, tmp_path):
    missing = tmp_path / "no_such_map.pt"
    done = _start(node, ros_env, f"map_file:={missing}")
    assert done.returncode == 2, done.stderr
    assert f"parameter map_file: {missing}: map file not found" in done.stderr
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a torch file")
    done = _start(node, ros_env, f"map_file:={broken}")
    assert done.returncode == 2 and f"parameter map_file: {broken}: not a readable map file" in done.stderr
    assert "Traceback" not in done.stderr


def test_an_out_of_range_value_stops_the_mapper_naming_it(ros_env):
    done = _start("mapper", ros_env, "mesh_period_s:=-1.0")
    assert done.returncode == 2
    assert "parameter mesh_period_s: expected >= 0, got -1.0" in done.stderr


@pytest.mark.parametrize(
    "param, expected",
    [
        ("base_to_camera:=[0.0, 0.0, 0.5]", "parameter base_to_camera: expected 7 numbers x y z qx qy qz qw"),
        ("gravity:=imu", "parameter gravity: expected one of extrinsic, floor, vector, got 'imu'"),
        ("base_to_camera:=[a, b]", "parameter base_to_camera: expected "),
    ],
)
def test_a_bad_frame_parameter_stops_the_tracker_naming_it(param, expected, ros_env):
    done = _start("tracker", ros_env, param)
    assert done.returncode == 2, done.stderr
    assert expected in done.stderr and "Traceback" not in done.stderr


def test_parameters_are_read_only_so_setting_one_at_run_time_is_refused(ros_env, monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from neb_slam_ros.frames import FrameOptions
    from neb_slam_ros.params import declare_config, declare_options

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, ros_env[key])
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("read_only_test", context=context)
        declare_config(node, "ci")
        opt = declare_options(node, FrameOptions)
        assert opt.base_to_camera == FrameOptions.base_to_camera  # a double array reads back as the tuple
        for name, value in (("map_frame", "elsewhere"), ("tracking.n_rays", 64), ("config", "tum")):
            (result,) = node.set_parameters([Parameter(name, value=value)])
            assert not result.successful and "read-only" in result.reason, (name, result.reason)
        assert node.get_parameter("map_frame").value == "map"
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
