"""Process-wide preparation of a process that runs the engine: :func:`prepare_engine_process`.

Two things are done once, before the first frame arrives, by whoever owns the process (the ROS nodes,
``neb-slam run``):

- **Short GIL turns.** The engine's threads (tracking, mapping, loop closure; in a ROS node also the
  executor's callbacks and a replay) run many short torch operations, each releasing the GIL and taking
  it back. A thread that wants it back waits until the holder's turn ends, up to the interpreter's switch
  interval (5 ms by default) whenever another thread runs Python: hundreds of operations per tracked
  frame then wait that long each. :data:`SWITCH_INTERVAL_S` shortens the turns.
- **One BLAS thread.** numpy and scipy call OpenBLAS, whose pool threads busy-wait for the next call
  after each one. The engine's BLAS calls are small (the loop closer's pose fits, the feature
  prediction), so a second thread gains nothing there, while its spinning, at the priority of the
  thread that started the pool, takes a core from tracking and mapping. :func:`prepare_engine_process`
  limits BLAS to the calling thread (torch's own intra-op threads are set per engine thread, see
  ``live.torch_threads``).
- **One-time costs paid at start.** The first torch optimizer imports the parts of torch it needs
  (seconds), the first backward pass starts autograd's engine, and the map's C++ kernels load. Done at
  start, none of it delays the first frame.

And per thread, :func:`lower_thread_priority`: mapping and loop closure yield the CPU to tracking
(``live.background_nice``), so that when every core is busy the thread that tracks the newest frame
is the one that keeps running.
"""

from __future__ import annotations

import os
import sys
import threading
import time

import torch
from threadpoolctl import threadpool_limits

#: the interpreter's switch interval in an engine process (Python's default: 0.005 s)
SWITCH_INTERVAL_S = 0.0005


def prepare_engine_process(grid_backend: str = "auto") -> float:
    """Shorten the GIL's turns and pay the engine's one-time costs (module docstring), the kernels' load
    as :func:`neb_slam_core.scene._ext.prepare` does for ``grid_backend``; returns the seconds spent. Safe
    to call more than once."""
    t0 = time.perf_counter()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    threadpool_limits(1, user_api="blas")
    p = torch.zeros(2, requires_grad=True)
    optimizer = torch.optim.Adam([p], lr=1e-3, fused=True)  # the engine's optimizers are fused Adams
    (p * p).sum().backward()
    optimizer.step()
    from neb_slam_core.scene import _ext

    _ext.prepare(grid_backend)
    return time.perf_counter() - t0


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform reports it)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def lower_thread_priority(nice: int) -> bool:
    """Raise the calling thread's nice value by ``nice`` (at most to 19): the scheduler then gives a core
    to the process' other threads first whenever they compete for it. Linux schedules threads one by
    one, so this touches no other thread; elsewhere, or with ``nice`` 0, nothing is done (False)."""
    if nice <= 0 or not sys.platform.startswith("linux"):
        return False
    tid = threading.get_native_id()
    os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    return True
