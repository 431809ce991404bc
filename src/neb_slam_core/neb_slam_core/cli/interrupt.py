"""Ctrl-C and SIGTERM for the ``neb-slam`` commands.

SIGTERM (what ``kill``, ``timeout``, systemd and container runtimes send) is turned into
:class:`Terminated`, a :class:`KeyboardInterrupt`, in the main thread. Every path that handles Ctrl-C
(``neb-slam run`` stops after the current frame and writes what it computed; a second interruption
aborts the writing) therefore handles SIGTERM the same way, and only the exit status tells them apart:
128 plus the signal's number, as a shell reports a process that the signal ended.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: exit status after Ctrl-C (128 + SIGINT)
EXIT_INTERRUPTED = 128 + signal.SIGINT
#: exit status after SIGTERM (128 + SIGTERM)
EXIT_TERMINATED = 128 + signal.SIGTERM


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived; raised by the handler :func:`sigterm_interrupts` installs."""


def exit_status(exc: KeyboardInterrupt) -> int:
    """The command's exit status after the interruption ``exc``: 143 for SIGTERM, 130 for Ctrl-C."""
    return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED


def describe(exc: KeyboardInterrupt) -> str:
    """How to name the interruption to the user: ``'SIGTERM'`` or ``'Ctrl-C'``."""
    return "SIGTERM" if isinstance(exc, Terminated) else "Ctrl-C"


def _raise_terminated(signum: int, frame) -> None:
    raise Terminated()


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """While the block runs, SIGTERM raises :class:`Terminated` in the main thread; the previous handler
    is restored afterwards. Outside the main thread (where Python cannot install handlers) it does
    nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class PendingInterrupt:
    """What :func:`deferred_interrupts` holds: the interruption that arrived (None: none yet)."""

    def __init__(self) -> None:
        self.exc: KeyboardInterrupt | None = None


@contextmanager
def deferred_interrupts() -> Iterator[PendingInterrupt]:
    """While the block runs, the first Ctrl-C or SIGTERM is only recorded (``pending.exc``: a
    :class:`KeyboardInterrupt` or :class:`Terminated`), so that the caller stops where its state is whole
    (after the current frame); a second one raises at once. The previous handlers are restored afterwards.
    Outside the main thread it records nothing and Ctrl-C raises as usual."""
    pending = PendingInterrupt()
    if threading.current_thread() is not threading.main_thread():
        yield pending
        return

    def on_signal(signum: int, frame) -> None:
        exc = Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()
        if pending.exc is not None:
            raise exc
        pending.exc = exc

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield pending
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
