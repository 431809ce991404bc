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
