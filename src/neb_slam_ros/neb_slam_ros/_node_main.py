"""The ``main()`` shared by every node executable: init rclpy, spin the nodes, shut down cleanly.

Ctrl-C (SIGINT), SIGTERM (what ``ros2 launch`` and systemd send) and a shutdown requested from elsewhere
all end the process with status 0 and no traceback, whenever they arrive once ``run_nodes`` runs (and,
for the executables, which start through :mod:`neb_slam_ros._launch`, while their modules import). A node
with a ``close()`` method (:class:`neb_slam_ros.node.NebNode`) gets it called once spinning ends (it writes
its output there, and may publish a last message: the context is still up after a signal or
:func:`request_stop`; if something else shut it down, our nodes' publishers drop the message instead of
raising). A bad parameter ends the process with status 2 and one line naming the parameter.

Order of the shutdown: a signal only asks the spin loop to stop (our handler, not rclpy's, which would
shut the ROS context down at once); then the executor stops, every node's ``close()`` runs, the nodes
are destroyed while the context is still up, and the context is shut down last: destroying a node
after its context can crash inside rcl's node teardown. A second Ctrl-C while the nodes close
interrupts ``close()``; a second SIGTERM ends the process at once.

The executor: rclpy's events executor where rclpy has it (Jazzy from rclpy 7.1.4), else the
single-threaded one. The single-threaded executor rebuilds its wait set in Python for every callback,
which at a camera's rate (colour, depth and camera info at 30 Hz) takes the node's process a large share
of a core and holds the GIL against the node's worker thread; the events executor dispatches from C++.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from neb_slam_ros.params import ParameterError

#: longest time a node's main thread stays in rcl's wait before Python sees a pending signal
SPIN_SLICE_S = 0.5
#: after a stop, how long the executor goes on running callbacks of messages already received
DRAIN_S = 0.5


def _executor(multi_threaded: bool):
    """The executor :func:`run_nodes` spins (module docstring)."""
    if multi_threaded:
        return MultiThreadedExecutor()
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return SingleThreadedExecutor()
    return EventsExecutor()


def run_node(make_node: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run one node until it is asked to stop; returns the process exit status.

    make_node: builds the node (usually the node class itself); called after ``rclpy.init``.
    args: the command line including ROS arguments (``--ros-args -r __ns:=/x -p name:=value``);
        None means ``sys.argv``.
    """
    return run_nodes([make_node], args, multi_threaded=False)


def _stop_on_signals(stop: threading.Event) -> dict:
    """SIGINT and SIGTERM set ``stop`` (once: then a second SIGINT raises KeyboardInterrupt and a second
    SIGTERM ends the process); returns the previous handlers."""

    def on_signal(signum, frame):
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    return {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}


#: set by :func:`request_stop`, SIGINT or SIGTERM: ends the spin of :func:`run_nodes`
_stop = threading.Event()


def request_stop() -> None:
    """End this process's :func:`run_nodes` as SIGINT does (a node whose work is over: the replay at the bag's
    end). The nodes' ``close()`` then runs with the ROS context still up, so they can still publish (the
    final mesh)."""
    _stop.set()


def run_nodes(
    makers: Sequence[Callable[[], Node | None]], args: Sequence[str] | None = None, multi_threaded: bool = True
) -> int:
    """Run several nodes in one process on one executor (multi-threaded by default); a maker may return
    None (that node is not wanted, e.g. no bag to replay)."""
    _stop.clear()
    previous = _stop_on_signals(_stop)  # before init: a signal during start-up is a requested stop too
    rclpy.init(args=list(args) if args is not None else None, signal_handler_options=SignalHandlerOptions.NO)
    executor = None
    nodes: list[Node] = []
    status = 0
    try:
        # the executor exists before a node logs that it started, so a signal right after that line
        # finds everything in place
        executor = _executor(multi_threaded)
        for make in makers:
            node = make()
            if node is not None:
                nodes.append(node)
                executor.add_node(node)
        # spin in slices rather than executor.spin(): the signal handler runs in Python, between slices,
        # so a stop is acted on within one
        while rclpy.ok() and not _stop.is_set():
            executor.spin_once(timeout_sec=SPIN_SLICE_S)
        # the callbacks of messages already received (a replay's last frames) run before the nodes close
        deadline = time.monotonic() + DRAIN_S
        while rclpy.ok() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # a second Ctrl-C during start-up, or the context shut down elsewhere
    except ParameterError as exc:
        print(f"[ERROR] neb_slam: {exc}", file=sys.stderr)
        status = 2
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
        for node in nodes:
            node.destroy_node()  # before the context's shutdown, unless something else shut it down
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return status
