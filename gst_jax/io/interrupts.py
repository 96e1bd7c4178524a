"""Stopping cleanly on SIGINT (Ctrl-C) and SIGTERM (what Slurm, Docker and Kubernetes send
before they kill a job): never in the middle of a checkpoint's write, and promptly.

    stops_noted()        inside, a stop signal is noted, not raised; the training loop asks
                         `stop_requested()` after every step and stops there, saving where
                         it is (an exact mid-epoch checkpoint)
    writes_completed()   a stop signal that arrives while a checkpoint is written takes
                         effect once the write is complete
    stops_end_the_process(grace_s)
                         for commands: a stop ends the process within `grace_s` even where
                         the main thread cannot notice it (inside an XLA compilation, which
                         cannot be interrupted), but never in the middle of a write

A signal the process ignores (SIGINT of a script's background job) stays ignored. Python runs
signal handlers in the main thread only, so only there are they installed.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import threading
from typing import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_noted: list[int] = []          # stop signals noted inside `stops_noted`
_noting = [False]               # whether `stops_noted` is active
_writing = threading.RLock()    # held while a checkpoint is written
# What a stop that ends the process before the main thread noticed it leaves behind (the
# training loop keeps it up to date as it saves).
_forced_exit_note = ["interrupted"]
# Files a forced exit removes first (a command's half-written output).
_removed_on_forced_exit: set[str] = set()


def _ours(signum: int) -> bool:
    """Whether this thread may handle `signum`: the main thread, unless the process ignores
    it."""
    return (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signum) is not signal.SIG_IGN)


@contextlib.contextmanager
def _handled(handler) -> Iterator[None]:
    """`handler` for every stop signal this thread may handle; the previous ones restored."""
    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS if _ours(s)}
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


@contextlib.contextmanager
def stops_noted() -> Iterator[None]:
    """Inside the block a stop signal is noted, not raised: an exception raised between two
    arbitrary bytecodes of JAX's Python, or in its garbage-collection callback (where Python
    swallows it), is no safe stop. `stop_requested()` says whether one came."""
    _noted.clear()
    _noting[0] = True
    try:
        with _handled(lambda signum, frame: _noted.append(signum)):
            yield
    finally:
        _noting[0] = False
        _noted.clear()


def stop_requested() -> str | None:
    """The name of the stop signal noted inside `stops_noted` ('SIGINT', 'SIGTERM'), or
    None."""
    return signal.Signals(_noted[0]).name if _noted else None


def set_forced_exit_note(text: str) -> None:
    """What to say if a stop ends the process before the main thread notices it: what the
    last save left and what a rerun will do."""
    _forced_exit_note[0] = text


@contextlib.contextmanager
def removed_on_forced_exit(path: str | os.PathLike) -> Iterator[None]:
    """Inside the block, a stop that ends the process (`stops_end_the_process`) removes
    `path` first: an output being written, which the block removes itself on any exception."""
    _removed_on_forced_exit.add(os.fspath(path))
    try:
        yield
    finally:
        _removed_on_forced_exit.discard(os.fspath(path))


@contextlib.contextmanager
def writes_completed() -> Iterator[None]:
    """Hold back stop signals inside the block (a checkpoint's write) and act on one at its
    end: inside `stops_noted` it stays noted, elsewhere it raises KeyboardInterrupt. Stopped
    in the middle of orbax's save, the main thread would leave its writer threads to fail at
    exit with a half-written checkpoint."""
    held: list[int] = []
    with _writing, _handled(lambda signum, frame: held.append(signum)):
        yield
    if held:
        if not _noting[0]:
            raise KeyboardInterrupt
        _noted.append(held[0])


@contextlib.contextmanager
def stops_end_the_process(grace_s: float) -> Iterator[None]:
    """For a command: a stop signal raises KeyboardInterrupt (SIGTERM as SIGINT does), and if
    the process still runs `grace_s` after it (its main thread may sit in an XLA
    compilation, where no Python runs) it ends with status 130 and the forced-exit note, once
    no write is in progress; a second stop signal ends it at once. The signal is seen as it
    arrives through `signal.set_wakeup_fd`, which C-level signal handling writes to whatever
    the main thread is doing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    receiver, sender = socket.socketpair()
    sender.setblocking(False)
    previous_fd = signal.set_wakeup_fd(sender.fileno(), warn_on_full_buffer=False)
    done = threading.Event()

    def next_stop(timeout: float | None) -> bool:
        """Wait for a stop signal's byte; False when the block has ended."""
        receiver.settimeout(timeout)
        while byte := receiver.recv(1):
            if byte[0] in STOP_SIGNALS:
                return not done.is_set()
        return False

    def watch() -> None:
        try:
            if not next_stop(None):
                return
            try:
                if not next_stop(grace_s):
                    return
            except TimeoutError:
                pass
        except OSError:                     # the sockets closed as the block ended
            return
        with _writing:                      # a write in progress completes first
            if not done.is_set():
                for path in list(_removed_on_forced_exit):
                    with contextlib.suppress(OSError):
                        os.unlink(path)
                print(f"\n{_forced_exit_note[0]}", file=sys.stderr, flush=True)
                os._exit(130)

    watcher = threading.Thread(target=watch, name="gst_jax stop watcher", daemon=True)
    watcher.start()
    try:
        with _handled(signal.default_int_handler):
            yield
    finally:
        done.set()
        signal.set_wakeup_fd(previous_fd)
        sender.close()                      # wakes the watcher, which returns
        watcher.join()
        receiver.close()
