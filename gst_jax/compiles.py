"""Counting XLA compilations, to show (and test) that jit caches hold: one program per shape.

    with count_compiles() as compiles:
        predict(params, key, batch)
    compiles.count, compiles.seconds
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import jax

# jax reports every backend compilation under this event name, with its duration.
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


class CompileCount:
    """Compilations (and their seconds) seen while registered with jax.monitoring."""

    def __init__(self):
        self.count, self.seconds = 0, 0.0

    def __call__(self, event: str, duration: float, **_) -> None:
        if event == COMPILE_EVENT:
            self.count += 1
            self.seconds += duration


@contextlib.contextmanager
def count_compiles() -> Iterator[CompileCount]:
    """Count the XLA compilations of this process inside the block (every thread)."""
    counter = CompileCount()
    jax.monitoring.register_event_duration_secs_listener(counter)
    try:
        yield counter
    finally:
        jax.monitoring.unregister_event_duration_listener(counter)
