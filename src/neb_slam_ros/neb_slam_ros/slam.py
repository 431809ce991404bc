"""``slam``: tracker, mapper and loop closer in one process, sharing one map.

Placeholder: it starts, logs one line and spins; the real node is a later issue.

Example::

    ros2 run neb_slam_ros slam                  # after colcon build and sourcing install/setup.bash
    python -m neb_slam_ros.slam --ros-args -r __ns:=/robot1/neb_slam
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rclpy.node import Node

from neb_slam_ros import NAMESPACE
from neb_slam_ros._node_main import run_node


class SlamNode(Node):
    """Placeholder; to come: the whole SLAM loop in one node, same topics as the separate nodes."""

    def __init__(self) -> None:
        super().__init__("slam", namespace=NAMESPACE)
        self.get_logger().info("neb_slam slam started (placeholder: the real node is a later issue)")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``slam`` executable; returns the exit status."""
    return run_node(SlamNode, args)


if __name__ == "__main__":
    sys.exit(main())
