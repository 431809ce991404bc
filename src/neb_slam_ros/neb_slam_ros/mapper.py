"""``mapper``: the neural-block map: joint optimisation over keyframes, map updates and the mesh.

Placeholder: it starts, logs one line and spins; the real node is a later issue.

Example::

    ros2 run neb_slam_ros mapper                  # after colcon build and sourcing install/setup.bash
    python -m neb_slam_ros.mapper --ros-args -r __ns:=/robot1/neb_slam
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rclpy.node import Node

from neb_slam_ros import NAMESPACE
from neb_slam_ros._node_main import run_node


class MapperNode(Node):
    """Placeholder; to come: optimise the block map from the tracker's keyframes, publish map_update and mesh."""

    def __init__(self) -> None:
        super().__init__("mapper", namespace=NAMESPACE)
        self.get_logger().info("neb_slam mapper started (placeholder: the real node is a later issue)")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapper`` executable; returns the exit status."""
    return run_node(MapperNode, args)


if __name__ == "__main__":
    sys.exit(main())
