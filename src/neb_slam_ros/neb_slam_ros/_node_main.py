"""The ``main()`` shared by every node executable: init rclpy, spin the nodes, shut down cleanly.

Ctrl-C (SIGINT), SIGTERM (what ``ros2 launch`` and systemd send) and a shutdown requested from elsewhere
all end the process with status 0 and no traceback, whenever they arrive (also during start-up). A node
with a ``close()`` method gets it called once spinning ends (it writes its output there: the ROS
context may already be shut down, so ``close`` must not publish). A bad parameter ends the process
with status 2 and one line naming the parameter.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node

from neb_slam_ros.params import ParameterError

try:  # the exception rcl raises when used with a context that a signal has already shut down
    from rclpy._rclpy_pybind11 import RCLError
except ImportError:  # pragma: no cover - layout of other rclpy builds
    RCLError = RuntimeError


class _PublisherWhileUp:
    """A publisher that drops its messages once the node's context is shut down. A signal shuts the
    context down while a worker thread may still be busy (a mapping step, a loop re-optimisation); what
    it publishes then has no receiver, and rclpy would raise in the worker and kill it."""

    def __init__(self, publisher, context):
        self._publisher = publisher
        self._context = context

    def publish(self, msg) -> None:
        try:
            self._publisher.publish(msg)
        except RCLError:
            if self._context.ok():
                raise

    def __getattr__(self, name):
        return getattr(self._publisher, name)


class WorkerNode(Node):
    """The base of our nodes, whose work runs in threads beside the executor's (a worker, the replay):
    their publishers go quiet (rather than raise) once a signal has shut the context down, so that work
    goes on to a clean stop, and ``close()`` then finishes it and writes the outputs."""

    def create_publisher(self, *args, **kwargs):
        return _PublisherWhileUp(super().create_publisher(*args, **kwargs), self.context)


#: longest time a node's main thread stays in rcl's wait before Python sees a pending signal
SPIN_SLICE_S = 0.5


def final_log(node: Node, text: str, level: str = "INFO") -> None:
    """A log line from ``close()``: the ROS context is shut down by then, so rclpy's logger (which also
    publishes to /rosout) would complain; this writes the same format to stderr only."""
    print(f"[{level}] [{time.time():.9f}] [{node.get_logger().name}]: {text}", file=sys.stderr, flush=True)


def run_node(make_node: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run one node until it is asked to stop; returns the process exit status.

    make_node: builds the node (usually the node class itself); called after ``rclpy.init``.
    args: the command line including ROS arguments (``--ros-args -r __ns:=/x -p name:=value``);
        None means ``sys.argv``.
    """
    return run_nodes([make_node], args, multi_threaded=False)


def run_nodes(makers: Sequence[Callable[[], Node | None]], args: Sequence[str] | None = None,
              multi_threaded: bool = True) -> int:
    """Run several nodes in one process on one executor (multi-threaded by default); a maker may return
    None (that node is not wanted, e.g. no bag to replay)."""
    # rclpy.init installs rclpy's SIGINT/SIGTERM handlers: they shut the context down, which makes a
    # spinning executor raise ExternalShutdownException (SIGTERM) or lets Python raise KeyboardInterrupt
    # (SIGINT).
    rclpy.init(args=list(args) if args is not None else None)
    executor = None
    nodes: list[Node] = []
    status = 0
    try:
        # the executor exists before a node logs that it started, so a signal right after that line
        # finds everything in place
        executor = MultiThreadedExecutor() if multi_threaded else SingleThreadedExecutor()
        for make in makers:
            node = make()
            if node is not None:
                nodes.append(node)
                executor.add_node(node)
        # spin in slices rather than executor.spin(): a SIGINT whose wake-up of the wait set is missed
        # (seen once in a quiet process at the end of a replay: nothing else woke it, and it never
        # stopped) is then acted on within a slice, when control is back in Python
        while rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_SLICE_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # the normal way to stop a node
    except ParameterError as exc:
        print(f"[ERROR] neb_slam: {exc}", file=sys.stderr)
        status = 2
    except RCLError:
        if rclpy.ok():
            raise  # a real failure, not the consequence of a requested shutdown
        # else: a signal shut the context down while the node was starting: a requested stop
    finally:
        if executor is not None:
            executor.shutdown()
        for node in nodes:
            close = getattr(node, "close", None)
            if close is not None:
                try:
                    close()
                except KeyboardInterrupt:
                    print(f"[{node.get_name()}] closing interrupted: its output may be incomplete", file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()  # no-op when a signal already shut the context down
    return status
