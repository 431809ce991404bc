"""``bag_replay``: plays the camera topics of a converted ROS 2 bag into the suite (and /clock).

Placeholder: it starts, logs one line and spins; the real node is a later issue.

Example::

    ros2 run neb_slam_ros bag_replay                  # after colcon build and sourcing install/setup.bash
    python -m neb_slam_ros.bag_replay --ros-args -r __ns:=/robot1/neb_slam
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rclpy.node import Node

from neb_slam_ros import NAMESPACE
from neb_slam_ros._node_main import run_node


class BagReplayNode(Node):
    """Placeholder; to come: publish a bag's colour, depth and camera_info at a chosen rate or in lockstep."""

    def __init__(self) -> None:
        super().__init__("bag_replay", namespace=NAMESPACE)
        self.get_logger().info("neb_slam bag_replay started (placeholder: the real node is a later issue)")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``bag_replay`` executable; returns the exit status."""
    return run_node(BagReplayNode, args)


if __name__ == "__main__":
    sys.exit(main())
