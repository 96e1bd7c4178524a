"""Ctrl-C (SIGINT) while files are written or steps run: deferred to the end of a checkpoint's
save, noticed between training steps."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Callable, Iterator


def _sigint_is_ours() -> bool:
    """Whether this thread may handle SIGINT: the main thread, unless the process ignores it
    (a background job of a script)."""
    return (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN)


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back SIGINT (Ctrl-C, `timeout -s INT`) inside the block and raise it at its end:
    interrupted inside orbax's save, the main thread would leave orbax's writer threads to
    fail at exit with a traceback and a half-written checkpoint. A SIGINT the process ignores
    (a background job of a script) stays ignored."""
    if not _sigint_is_ours():
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda *_: received.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_noticed() -> Iterator[Callable[[], None]]:
    """Inside the block SIGINT raises KeyboardInterrupt as usual and is also remembered; call
    the yielded check at safe points (after each training step) to raise a remembered one.
    Python swallows an exception raised in a garbage-collection callback ("Exception ignored
    in _xla_gc_callback"), so a Ctrl-C that lands in JAX's would otherwise be lost and the
    run go on (and print "Exception ignored ... KeyboardInterrupt", which is kept quiet here).
    A SIGINT the process ignores stays ignored."""
    received = []

    def check() -> None:
        if received:
            received.clear()
            raise KeyboardInterrupt

    if not _sigint_is_ours():
        yield check
        return

    def remember_and_raise(signum, frame):
        received.append(True)
        raise KeyboardInterrupt

    def report_unless_interrupt(unraisable) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            previous_hook(unraisable)

    previous, previous_hook = signal.signal(signal.SIGINT, remember_and_raise), sys.unraisablehook
    sys.unraisablehook = report_unless_interrupt
    try:
        yield check
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook
