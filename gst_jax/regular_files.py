"""Files read from folders others fill (weights, configs, checkpoints): regular files only,
within a size bound.

A FIFO named model.safetensors blocks its reader until something writes to it, and a symbolic
link to /dev/zero is read until memory runs out. So such a file is taken only where it is a
regular file (a symbolic link is followed, and what it names must be one) of at most a bound,
else refused in one line before anything is read. It is opened without blocking (a FIFO put
there after the check opens at once, and the open descriptor is checked again) and read in
chunks, never past the bound (a file that grows while it is read is refused too). Missing or
unreadable files raise the OSError `open` would, so that each caller keeps its own words for
them. No jax here.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from gst_jax.errors import DataError

# A file is read this much at a time.
CHUNK_BYTES = 2**20

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def open_regular(path: str | os.PathLike, max_bytes: int, bound: str,
                 error: type[Exception] = DataError) -> BinaryIO:
    """`path` opened for reading (binary), once it is checked to be a regular file of at most
    `max_bytes`; `error` (one line naming the file, what it is or its size, and `bound`, the
    constant that sets max_bytes) otherwise. FileNotFoundError and other OSErrors as `open`."""
    path = Path(path)
    _check(path, os.stat(path), max_bytes, bound, error)
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        _check(path, os.fstat(descriptor), max_bytes, bound, error)
        return os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise


def read_regular(path: str | os.PathLike, max_bytes: int, bound: str,
                 error: type[Exception] = DataError) -> bytes:
    """The bytes of `path`, a regular file of at most `max_bytes` (`open_regular`), read
    CHUNK_BYTES at a time and never past the bound."""
    path = Path(path)
    chunks, total = [], 0
    with open_regular(path, max_bytes, bound, error) as file:
        while chunk := file.read(min(CHUNK_BYTES, max_bytes + 1 - total)):
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:
                raise error(f"{path}: grew past the {max_bytes} bytes it may hold ({bound}) "
                            "while it was read: refused")
    return b"".join(chunks)


def _check(path: Path, info: os.stat_result, max_bytes: int, bound: str,
           error: type[Exception]) -> None:
    if not stat.S_ISREG(info.st_mode):
        kind = next((name for test, name in _KINDS if test(info.st_mode)), "something else")
        link = f" (a link to {os.path.realpath(path)})" if path.is_symlink() else ""
        raise error(f"{path} is {kind}{link}, not a regular file: refused unread (name the "
                    "file itself)")
    if info.st_size > max_bytes:
        raise error(f"{path}: {info.st_size} bytes, more than the {max_bytes} it may hold "
                    f"({bound}): refused unread")
