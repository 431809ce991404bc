"""The skeleton every node of the suite is built on: :class:`NebNode`.

A node of ours is an rclpy node whose real work (tracking, mapping, loop checks, the replay) runs in one
worker thread beside the executor's. The executor thread only runs callbacks: they put messages into
the node's queues under :attr:`NebNode.cond` and notify it. The worker owns the engine state (the map,
the keyframes), so nothing else touches it; services and timers that need that state (``save_mesh``,
``save_map``, the periodic mesh) are handed to the worker as requests (:meth:`NebNode.worker_service`,
:meth:`NebNode.worker_timer`) and, for a service, the executor thread waits for the worker's answer. A
node whose engine runs threads of its own (the ``mapper``'s mapping side) names the lock they change the
state under (:meth:`NebNode.state_lock`), and requests run holding it.

A subclass declares its parameters through the constructor (the engine config and its options
dataclass), says what it waits for (:meth:`~NebNode.has_work`), takes it under the lock
(:meth:`~NebNode.take_work`), does it outside the lock (:meth:`~NebNode.do_work`), and writes its
outputs in :meth:`~NebNode.finish`. :meth:`~NebNode.close` (called once by
:func:`neb_slam_ros._node_main.run_nodes` after spinning ends) stops the worker, joins it and then runs
``finish()``. A node whose worker is not a wait-for-work loop (the replay) overrides
:meth:`~NebNode.work_loop`.

Publishers created by a node drop their messages instead of raising once the ROS context is shut down:
a worker busy with a mapping step, or ``close()`` publishing the final mesh, may outlive the context when
something else shut it down.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rclpy.node import Node
from std_srvs.srv import Trigger

from neb_slam_core.engine_process import lower_thread_priority, prepare_engine_process
from neb_slam_ros import NAMESPACE
from neb_slam_ros.params import declare_config, declare_options

try:  # the exception rcl raises when used with a context that a signal has already shut down
    from rclpy._rclpy_pybind11 import RCLError
except ImportError:  # pragma: no cover - layout of other rclpy builds
    RCLError = RuntimeError


class PublisherWhileUp:
    """A publisher that drops its messages once the node's context is shut down (see the module
    docstring); everything else is rclpy's publisher."""

    def __init__(self, publisher, context):
        self._publisher = publisher
        self._context = context

    def publish(self, msg) -> None:
        try:
            self._publisher.publish(msg)
        except RCLError:
            if self._context.ok():
                raise

    def wait_for_all_acked(self, timeout) -> bool:
        """rclpy's, or False at once when the context is shut down (nothing can be acknowledged then)."""
        try:
            return self._context.ok() and self._publisher.wait_for_all_acked(timeout)
        except RCLError:
            if self._context.ok():
                raise
            return False

    def __getattr__(self, name):
        return getattr(self._publisher, name)


@dataclass
class _Request:
    handler: Callable[[], str]
    key: str
    coalesce: bool
    done: threading.Event = field(default_factory=threading.Event)
    reply: list = field(default_factory=list)


class _RequestQueue:
    """Work that the executor thread hands to the worker; guarded by the node's condition variable."""

    def __init__(self, cond: threading.Condition):
        self._cond = cond
        self._pending: list[_Request] = []

    def __bool__(self) -> bool:
        return bool(self._pending)

    def submit(self, handler: Callable[[], str], key: str, coalesce: bool = False) -> _Request:
        """Queue ``handler`` (from any thread). With ``coalesce``, a request already pending under ``key``
        makes this one a no-op (a second periodic mesh would only repeat the first)."""
        request = _Request(handler, key, coalesce)
        with self._cond:
            if coalesce and any(r.key == key for r in self._pending):
                request.done.set()
                return request
            self._pending.append(request)
            self._cond.notify_all()
        return request

    def take(self) -> list[_Request]:
        """The pending requests, removed (call with the condition held)."""
        taken, self._pending = self._pending, []
        return taken


class NebNode(Node):
    """The base of the suite's nodes; see the module docstring.

    Args:
        name: the node's name (in namespace :data:`neb_slam_ros.NAMESPACE`).
        options: the node's own parameters, a frozen dataclass (:func:`~neb_slam_ros.params.declare_options`).
        with_config: declare the engine configuration (:attr:`cfg`, every config leaf a parameter).
        join_timeout_s: how long :meth:`close` waits for the worker to finish what it is doing.
    """

    #: the worker maps or closes loops: it runs ``live.background_nice`` nicer than the tracking
    #: nodes' workers, so that tracking keeps a core when all are busy
    background = False

    def __init__(
        self,
        name: str,
        options: type | None = None,
        with_config: bool = True,
        join_timeout_s: float = 600.0,
        **kwargs: Any,
    ) -> None:
        super().__init__(name, namespace=kwargs.pop("namespace", NAMESPACE), **kwargs)
        self.cfg = declare_config(self) if with_config else None
        if self.cfg is not None:  # an engine node: its first frame pays no one-time cost
            prepare_engine_process(self.cfg.grid_backend)
        self.opt = declare_options(self, options) if options is not None else None
        self.cond = threading.Condition()
        self._stopping = threading.Event()
        self._requests = _RequestQueue(self.cond)
        self._join_timeout_s = join_timeout_s
        self._worker: threading.Thread | None = None

    def create_publisher(self, *args, **kwargs):
        return PublisherWhileUp(super().create_publisher(*args, **kwargs), self.context)

    # ------------------------------------------------------------------ what a subclass provides

    def has_work(self) -> bool:
        """Something for :meth:`do_work` is queued (called with :attr:`cond` held)."""
        return False

    def take_work(self) -> Any:
        """Remove and return what :meth:`do_work` should do next (called with :attr:`cond` held)."""
        return None

    def do_work(self, work: Any) -> None:
        """Do ``work`` (in the worker thread, without the lock)."""

    def finish(self) -> None:
        """Write the node's outputs after the worker stopped (in the thread that called :meth:`close`)."""

    def state_lock(self) -> contextlib.AbstractContextManager:
        """Held while a request (a service, a timer's work) runs: a node whose engine state also changes in
        threads of its own returns the lock those threads hold while they change it (default: none)."""
        return contextlib.nullcontext()

    # ------------------------------------------------------------------ the worker

    @property
    def stopping(self) -> bool:
        """:meth:`close` was called: the worker ends after what it is doing."""
        return self._stopping.is_set()

    def wait_stopping(self, timeout_s: float) -> bool:
        """Sleep up to ``timeout_s``, waking at once on a stop; True when stopping."""
        return self._stopping.wait(timeout_s)

    def start_worker(self) -> None:
        """Start the worker thread (at the end of the subclass' constructor, once its state exists)."""
        self._worker = threading.Thread(target=self._run_worker, name=f"{self.get_name()}-worker", daemon=True)
        self._worker.start()

    def _run_worker(self) -> None:
        threads = self.cfg.live.torch_threads if self.cfg is not None else 0
        if threads > 0:  # the engine config's thread count, in the thread that runs the engine
            import torch

            torch.set_num_threads(threads)
        if self.background and self.cfg is not None:
            lower_thread_priority(self.cfg.live.background_nice)
        self.work_loop()

    def work_loop(self) -> None:
        """Wait for work or requests, take them under the lock, do them outside it, until stopped."""
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.stopping or self._requests or self.has_work(), timeout=1.0)
                if self.stopping:
                    return
                work = self.take_work()
                requests = self._requests.take()  # served after the work that came before them
            self.do_work(work)
            self._serve(requests)

    def _serve(self, requests: list[_Request]) -> None:
        for request in requests:
            if self.stopping or not self.context.ok():
                request.reply.append((False, "the node is shutting down"))
            else:
                try:
                    with self.state_lock():
                        request.reply.append((True, request.handler()))
                except Exception as exc:  # reported to the caller; the node goes on
                    request.reply.append((False, f"{type(exc).__name__}: {exc}"))
                    self.get_logger().error(f"{request.key} failed: {type(exc).__name__}: {exc}")
            request.done.set()

    # ------------------------------------------------------------------ services and timers run by the worker

    def worker_service(self, name: str, handler: Callable[[], str], timeout_s: float = 600.0) -> None:
        """A ``std_srvs/Trigger`` service ``name`` answered by ``handler()`` in the worker thread: success
        with its return value as the message, or failure with the exception it raised."""

        def serve(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            queued = self._requests.submit(handler, name)
            queued.done.wait(timeout=timeout_s)
            response.success, response.message = queued.reply[0] if queued.reply else (False, f"{name} timed out")
            return response

        self.create_service(Trigger, name, serve)

    def worker_timer(self, period_s: float, handler: Callable[[], str], key: str):
        """Run ``handler()`` in the worker every ``period_s`` (a tick while the last one is still queued is
        dropped); returns the rclpy timer."""
        return self.create_timer(period_s, lambda: self.submit(handler, key, coalesce=True))

    def submit(self, handler: Callable[[], str], key: str, coalesce: bool = False) -> _Request:
        """Hand ``handler()`` to the worker from any thread; the returned request's ``done`` event is set once
        it ran, and its ``reply`` then holds ``(success, message)``."""
        return self._requests.submit(handler, key, coalesce)

    # ------------------------------------------------------------------ shutdown

    def notify(self) -> None:
        """Wake the worker (after queueing work under :attr:`cond` from outside a callback)."""
        with self.cond:
            self.cond.notify_all()

    def close(self) -> None:
        """Stop the worker (it finishes what it is doing), then :meth:`finish`."""
        self._stopping.set()
        self.notify()
        if self._worker is not None:
            self._worker.join(timeout=self._join_timeout_s)
        self.finish()

    def final_log(self, text: str, level: str = "INFO") -> None:
        """A log line from :meth:`finish`: the ROS context may be shut down by then (from outside the
        process), and rclpy's logger, which also publishes to /rosout, would complain; this writes the same
        format to stderr only."""
        print(f"[{level}] [{time.time():.9f}] [{self.get_logger().name}]: {text}", file=sys.stderr, flush=True)
