"""``loop_closer``: bag-of-words place recognition over keyframes and pose correction.

Placeholder: it starts, logs one line and spins; the real node is a later issue.

Example::

    ros2 run neb_slam_ros loop_closer                  # after colcon build and sourcing install/setup.bash
    python -m neb_slam_ros.loop_closer --ros-args -r __ns:=/robot1/neb_slam
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rclpy.node import Node

from neb_slam_ros import NAMESPACE
from neb_slam_ros._node_main import run_node


class LoopCloserNode(Node):
    """Placeholder; to come: detect loops among keyframes, publish corrected keyframe poses on loop_closure."""

    def __init__(self) -> None:
        super().__init__("loop_closer", namespace=NAMESPACE)
        self.get_logger().info("neb_slam loop_closer started (placeholder: the real node is a later issue)")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``loop_closer`` executable; returns the exit status."""
    return run_node(LoopCloserNode, args)


if __name__ == "__main__":
    sys.exit(main())
