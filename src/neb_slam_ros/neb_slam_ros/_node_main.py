"""The ``main()`` shared by every node executable: init rclpy, spin one node, shut down cleanly.

Ctrl-C (SIGINT), SIGTERM (what ``ros2 launch`` and systemd send) and a shutdown requested from elsewhere
all end the process with status 0 and no traceback, whenever they arrive (also during start-up).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

try:  # the exception rcl raises when used with a context that a signal has already shut down
    from rclpy._rclpy_pybind11 import RCLError
except ImportError:  # pragma: no cover - layout of other rclpy builds
    RCLError = RuntimeError


def run_node(make_node: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run one node until it is asked to stop; returns the process exit status.

    make_node: builds the node (usually the node class itself); called after ``rclpy.init``.
    args: the command line including ROS arguments (``--ros-args -r __ns:=/x -p name:=value``);
        None means ``sys.argv``.
    """
    # rclpy.init installs rclpy's SIGINT/SIGTERM handlers: they shut the context down, which makes a
    # spinning executor raise ExternalShutdownException (SIGTERM) or lets Python raise KeyboardInterrupt
    # (SIGINT).
    rclpy.init(args=list(args) if args is not None else None)
    executor: SingleThreadedExecutor | None = None
    node: Node | None = None
    try:
        # the executor exists before the node logs that it started, so a signal right after that line
        # finds everything in place
        executor = SingleThreadedExecutor()
        node = make_node()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # the normal way to stop a node
    except RCLError:
        if rclpy.ok():
            raise  # a real failure, not the consequence of a requested shutdown
        # else: a signal shut the context down while the node was starting: a requested stop
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()  # no-op when a signal already shut the context down
    return 0
