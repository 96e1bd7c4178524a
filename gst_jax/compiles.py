"""Counting XLA compilations, to show (and test) that jit caches hold: one program per shape,
and keeping compiled programs on disk for the next process.

    with count_compiles() as compiles:
        predict(params, key, batch)
    compiles.count, compiles.seconds

    use_persistent_cache("~/.cache/my_robot/xla")    # a restarted process compiles nothing

Counting also warns before compiling hits Linux's limit on memory maps (below). A program
loaded from the persistent cache counts too (jax reports it under the same event, with the
seconds of reading it).
"""

from __future__ import annotations

import contextlib
import os
import warnings
from pathlib import Path
from typing import Iterator

import jax

# jax reports every backend compilation under this event name, with its duration.
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
# Every program XLA compiles for a CPU holds memory maps (about 2,300 each for univ's training
# steps, measured: 94,273 after 41 programs). At the kernel's vm.max_map_count (65530 by
# default) the next compile fails with LLVM's "Cannot allocate memory" and a segfault, with
# nothing else to explain it; so warn once the process holds this share of the limit.
MAP_COUNT_WARNING_SHARE = 0.75


def memory_maps() -> tuple[int, int] | None:
    """(memory maps this process holds, vm.max_map_count) on Linux; None elsewhere."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            held = sum(1 for _ in maps)
        return held, int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


class CompileCount:
    """Compilations (and their seconds) seen while registered with jax.monitoring."""

    def __init__(self):
        self.count, self.seconds = 0, 0.0
        self.warned_of_maps = False

    def __call__(self, event: str, duration: float, **_) -> None:
        if event == COMPILE_EVENT:
            self.count += 1
            self.seconds += duration
            self._check_memory_maps()

    def _check_memory_maps(self) -> None:
        if self.warned_of_maps or (maps := memory_maps()) is None:
            return
        held, limit = maps
        if held > MAP_COUNT_WARNING_SHARE * limit:
            self.warned_of_maps = True
            warnings.warn(f"this process holds {held} memory maps of the {limit} Linux allows "
                          "(vm.max_map_count), and each compiled program adds more; at the "
                          "limit compiling fails (LLVM 'Cannot allocate memory', then a "
                          "segmentation fault). Raise it: sudo sysctl -w "
                          "vm.max_map_count=262144", stacklevel=2)


@contextlib.contextmanager
def count_compiles() -> Iterator[CompileCount]:
    """Count the XLA compilations of this process inside the block (every thread)."""
    counter = CompileCount()
    jax.monitoring.register_event_duration_secs_listener(counter)
    try:
        yield counter
    finally:
        jax.monitoring.unregister_event_duration_listener(counter)


def use_persistent_cache(directory: str | os.PathLike) -> None:
    """Keep every program this process compiles in `directory` (created if need be), and look
    there before compiling: JAX's persistent compilation cache, set for the whole process.
    Programs are kept however quickly they compiled (a small model's step may take under
    JAX's default threshold of 1 s and would otherwise be compiled again by every process).
    The folder is trusted: whoever can write to it can run code in this process."""
    path = os.path.abspath(os.path.expanduser(os.fspath(directory)))
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if jax.config.jax_compilation_cache_dir != path:
        jax.config.update("jax_compilation_cache_dir", path)
        # jax decides once per process whether it has a cache: let it decide again.
        from jax.experimental.compilation_cache import compilation_cache

        compilation_cache.reset_cache()
