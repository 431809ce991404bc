"""Work that service calls and timers hand to a node's worker thread (``save_mesh``, ``save_map``,
``publish_mesh``): the map is only ever touched by that thread, so the executor thread queues the work
and, for a service, waits for the reply.

The queue shares the node's condition variable, so one wait in the worker covers its own input and
these requests. A request ``what`` runs the node's method ``_do_<what>()``, whose return value is the
service's message.
"""

from __future__ import annotations

import threading

from std_srvs.srv import Trigger

#: requests that a second copy, queued while the first is pending, would only repeat
COALESCED = ("publish_mesh",)


class Requests:
    def __init__(self, cond: threading.Condition):
        self._cond = cond
        self._pending: list[tuple[str, threading.Event, list]] = []

    def __bool__(self) -> bool:
        return bool(self._pending)

    def submit(self, what: str) -> tuple[threading.Event, list]:
        """Queue ``what`` (from any thread); returns the event set when done and the reply list."""
        done, reply = threading.Event(), []
        with self._cond:
            if what in COALESCED and any(w == what for w, _, _ in self._pending):
                done.set()
                return done, reply
            self._pending.append((what, done, reply))
            self._cond.notify_all()
        return done, reply

    def serve(self, what: str, response: Trigger.Response, timeout_s: float = 600.0) -> Trigger.Response:
        """A Trigger service handler: queue ``what`` and answer with its outcome."""
        done, reply = self.submit(what)
        done.wait(timeout=timeout_s)
        response.success, response.message = (reply[0] if reply else (False, f"{what} timed out"))
        return response

    def take(self) -> list[tuple[str, threading.Event, list]]:
        """The pending requests, removed (call with the condition held)."""
        taken, self._pending = self._pending, []
        return taken

    @staticmethod
    def run(taken, node, stopping: bool) -> None:
        """Run ``taken`` requests on ``node`` in the worker thread; refused while ``stopping``."""
        for what, done, reply in taken:
            if stopping or not node.context.ok():
                reply.append((False, "the node is shutting down"))
            else:
                try:
                    reply.append((True, getattr(node, "_do_" + what)()))
                except Exception as exc:  # reported to the caller; the node goes on
                    reply.append((False, f"{type(exc).__name__}: {exc}"))
                    node.get_logger().error(f"{what} failed: {type(exc).__name__}: {exc}")
            done.set()
