"""Folders whose contents this process runs or trusts: owned by this user, writable by no one
else (the rule ssh applies to a user's keys).

JAX's persistent compilation cache holds machine code that a later process loads and runs:
whoever can write to the folder can run code in every process that uses it. So a cache
folder is used only when this user owns it and no group or other user may write to it, nor
to a folder above it (a folder above may be root's, or world-writable with the sticky bit,
as /tmp is: there no one else can rename or replace what is ours). No jax here: the commands
that compute nothing check their folder without importing it.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from gst_jax.errors import DataError


def private_folder(directory: str | os.PathLike, what: str = "compilation cache") -> Path:
    """`directory` as an absolute path, created (mode 0700) if missing, once it is checked to
    be this user's alone; DataError naming the fix otherwise."""
    if not os.fspath(directory).strip():
        raise DataError(f"the {what} folder is empty: name a folder, e.g. "
                        "~/.cache/gst_jax/xla")
    path = Path(os.path.abspath(os.path.expanduser(os.fspath(directory))))
    if not path.exists():
        _check_ancestors(path.parent, path, what)
        try:
            path.mkdir(mode=0o700, parents=True)
        except FileExistsError:
            pass                                   # made by another process meanwhile
        except OSError as error:
            raise DataError(f"cannot create the {what} folder {path}: "
                            f"{error.strerror}") from None
    info = path.lstat()
    if stat.S_ISLNK(info.st_mode):
        raise DataError(f"the {what} folder {path} is a symbolic link: name the folder it "
                        f"points to ({os.path.realpath(path)}) once it is yours alone")
    if not stat.S_ISDIR(info.st_mode):
        raise DataError(f"the {what} folder {path} is not a folder")
    if info.st_uid != os.geteuid():
        raise DataError(f"the {what} folder {path} belongs to another user (uid "
                        f"{info.st_uid}): whoever owns it could run code in this process; use a "
                        f"folder of your own, e.g. ~/.cache/gst_jax/xla")
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise DataError(f"the {what} folder {path} is writable by others (mode "
                        f"{stat.S_IMODE(info.st_mode):o}): anyone who can write there could "
                        f"run code in this process; chmod go-w {path}, or use another folder")
    _check_ancestors(path.parent, path, what)
    return path


def _check_ancestors(folder: Path, path: Path, what: str) -> None:
    """Every existing folder from `folder` up: root's or ours, and writable by no one else
    unless sticky (others can then add their own entries, not rename ours)."""
    for above in (folder, *folder.parents):
        try:
            info = above.stat()
        except FileNotFoundError:
            continue
        if info.st_uid not in (0, os.geteuid()):
            raise DataError(f"the {what} folder {path} lies in {above}, which belongs to "
                            f"another user (uid {info.st_uid}), who could replace it; use a "
                            f"folder of your own, e.g. ~/.cache/gst_jax/xla")
        writable = info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        if writable and not info.st_mode & stat.S_ISVTX:
            raise DataError(f"the {what} folder {path} lies in {above}, which others may write "
                            f"to (mode {stat.S_IMODE(info.st_mode):o}), so they could replace "
                            f"it; use a folder of your own, e.g. ~/.cache/gst_jax/xla")
