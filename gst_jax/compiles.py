"""Counting XLA compilations, to show (and test) that jit caches hold: one program per shape,
and keeping compiled programs on disk for the next process.

    with count_compiles() as compiles:
        predict(params, key, batch)
    compiles.count, compiles.seconds

    use_persistent_cache("~/.cache/my_robot/xla")    # a restarted process compiles nothing

The persistent cache holds machine code that later processes run, so its folder must be
this user's alone (`gst_jax.private_folders`), and every entry carries a checksum of its key
and contents: an entry damaged on disk, or not written through this module (another
program's, another version's), is compiled afresh and replaced, with a warning, instead of
being loaded (a damaged executable can kill the process with SIGILL).

Counting also warns before compiling hits Linux's limit on memory maps (below). A program
loaded from the persistent cache counts too (jax reports it under the same event, with the
seconds of reading it).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import warnings
from pathlib import Path
from typing import Iterator

import jax
from jax._src import compilation_cache as jax_cache, lru_cache
from jax._src.compilation_cache_interface import CacheInterface

from gst_jax.private_folders import private_folder

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

    def __call__(self, event: str, duration_secs: float, **_: str | int) -> None:
        if event == COMPILE_EVENT:
            self.count += 1
            self.seconds += duration_secs
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


def use_persistent_cache(directory: str | os.PathLike, min_compile_s: float | None = 0.0
                         ) -> None:
    """Keep every program this process compiles in `directory` (created, mode 0700, if need
    be), and look there before compiling: JAX's persistent compilation cache, set for the
    whole process, its entries checked (module docstring). Programs are kept however quickly
    they compiled (`min_compile_s` 0: a small model's step may take under JAX's default
    threshold of 1 s and would otherwise be compiled again by every process; None keeps
    JAX's). DataError where the folder is not this user's alone."""
    path = str(private_folder(directory))
    check_cache_entries()
    if min_compile_s is not None:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_s)
    # jax's flags are attributes its config makes at runtime, unknown to its stubs.
    if jax.config.jax_compilation_cache_dir != path:  # type: ignore[attr-defined]
        jax.config.update("jax_compilation_cache_dir", path)
        # jax decides once per process whether it has a cache: let it decide again.
        jax_cache.reset_cache()


# A checked entry: this header, the SHA-256 of its key and value, then the value jax stores.
ENTRY_HEADER = b"gst_jax.xla/1\n"


def _digest(key: str, value: bytes) -> bytes:
    return hashlib.sha256(key.encode() + b"\0" + value).digest()


class CheckedCache(CacheInterface):
    """jax's file cache with a checksum on every entry: `get` returns only what `put` stored
    under the same key, intact; anything else is a miss, with a warning (once a process)."""

    def __init__(self, base: CacheInterface):
        self._base = base
        self._path = base._path
        self._warned = False

    def get(self, key: str) -> bytes | None:
        entry = self._base.get(key)
        if entry is None:
            return None
        size = len(ENTRY_HEADER) + hashlib.sha256().digest_size
        value = entry[size:]
        if entry[:len(ENTRY_HEADER)] == ENTRY_HEADER and entry[len(ENTRY_HEADER):size] == (
                _digest(key, value)):
            return value
        if not self._warned:
            self._warned = True
            warnings.warn(f"the compilation cache {self._path} holds an entry that is damaged "
                          f"or was not written by gst_jax ({key}): compiling afresh and "
                          "replacing it (and any more such entries, without a word)",
                          stacklevel=2)
        return None

    def put(self, key: str, value: bytes) -> None:
        # jax puts only after a miss, and its cache keeps an existing entry: remove the one
        # `get` refused (a race with another process's good entry costs one compile).
        (Path(self._path) / f"{key}{lru_cache._CACHE_SUFFIX}").unlink(missing_ok=True)
        self._base.put(key, ENTRY_HEADER + _digest(key, value) + value)


_jax_file_cache = jax_cache.get_file_cache


def _checked_file_cache(path: str):
    made = _jax_file_cache(path)
    return None if made is None else (CheckedCache(made[0]), made[1])


def check_cache_entries() -> None:
    """Every persistent cache jax opens in this process, whatever set its folder, checks its
    entries (CheckedCache); a cache already open is opened again."""
    if jax_cache.get_file_cache is not _checked_file_cache:
        jax_cache.get_file_cache = _checked_file_cache
        jax_cache.reset_cache()


# Set on import: a process that runs gst_jax's models (`gst_jax.predict` imports this module)
# reads and writes checked entries whatever set its cache folder (JAX_COMPILATION_CACHE_DIR
# included), so that processes sharing a folder never take each other's entries for foreign.
check_cache_entries()
