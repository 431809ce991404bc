"""The ROS package is built by colcon (ament_python), not pip-installed into the venv: its tests import it
from the source tree, as the node processes they start do (PYTHONPATH)."""

import sys
from pathlib import Path

ROS_PACKAGE_ROOT = Path(__file__).resolve().parents[2] / "src" / "neb_slam_ros"
if str(ROS_PACKAGE_ROOT) not in sys.path:
    sys.path.insert(0, str(ROS_PACKAGE_ROOT))
