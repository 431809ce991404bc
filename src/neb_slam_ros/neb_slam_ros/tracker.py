"""``tracker``: per-frame camera pose, keyframes and neural-block allocation.

Placeholder: it starts, logs one line and spins; the real node is a later issue.

Example::

    ros2 run neb_slam_ros tracker                  # after colcon build and sourcing install/setup.bash
    python -m neb_slam_ros.tracker --ros-args -r __ns:=/robot1/neb_slam
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rclpy.node import Node

from neb_slam_ros import NAMESPACE
from neb_slam_ros._node_main import run_node


class TrackerNode(Node):
    """Placeholder; to come: track each RGB-D frame against the map, publish pose, odometry, path, keyframes, blocks."""

    def __init__(self) -> None:
        super().__init__("tracker", namespace=NAMESPACE)
        self.get_logger().info("neb_slam tracker started (placeholder: the real node is a later issue)")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``tracker`` executable; returns the exit status."""
    return run_node(TrackerNode, args)


if __name__ == "__main__":
    sys.exit(main())
