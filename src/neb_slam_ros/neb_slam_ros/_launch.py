"""The node executables' entry points (``ros2 run neb_slam_ros <node>``).

A node's module imports torch, rclpy and the engine, which takes seconds before its ``main()`` can take
over Ctrl-C and SIGTERM (``_node_main.run_nodes``). Started from here, a stop that arrives during those
imports also ends the process with status 0 and one line, instead of a KeyboardInterrupt traceback and
status 130: this module imports nothing heavy, installs a handler that exits, then imports the node's
module and runs its ``main()``, whose own handler replaces this one.

The handler ends the process at once (``os._exit``) rather than raising ``SystemExit``: an exception
raised in a signal handler surfaces inside whichever import is running, and a C extension whose
initialisation it interrupts (rclpy's) turns it into ``ImportError: initialization failed``. Nothing
needs cleaning up before the node's ``main()`` runs.
"""

from __future__ import annotations

import importlib
import os
import signal
import sys

#: executable name = module in neb_slam_ros exposing main() (setup.py lists the same)
NODES = ("tracker", "mapper", "loop_closer", "bag_replay", "slam")


def _run(node: str) -> int:
    def stop_during_start_up(signum, frame):
        print(
            f"[INFO] neb_slam {node}: stopped during start-up ({signal.Signals(signum).name})",
            file=sys.stderr,
            flush=True,
        )
        os._exit(0)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop_during_start_up)
    return importlib.import_module(f"{__package__}.{node}").main()


def _entry_point(node: str):
    def main() -> int:
        return _run(node)

    main.__name__ = node
    main.__doc__ = f"Entry point of the ``{node}`` executable."
    return main


tracker, mapper, loop_closer, bag_replay, slam = (_entry_point(node) for node in NODES)
