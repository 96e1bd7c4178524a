"""Checkpoints of a training state: orbax, checksummed, restored with a fall-back."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import jax
import numpy as np

from gst_jax.errors import RunError
from gst_jax.io.interrupts import writes_completed

__all__ = ["Checkpointer", "Restored", "write_atomically"]


def _orbax():
    """orbax.checkpoint, imported when a checkpoint is first written or read: importing it
    takes ~0.15 s, which a restarted robot that only loads a shipped model should not wait."""
    import orbax.checkpoint
    return orbax.checkpoint


class Restored(NamedTuple):
    """A checkpoint read back: the state, the run's config, the metrics records of the
    epochs it completed (one per epoch), its epoch, and, for a checkpoint taken inside an
    epoch, where in it (`progress`, as saved)."""

    state: Any
    config: dict
    records: list
    epoch: int
    progress: dict | None = None


class Checkpointer:
    """Saves `{state, config, metrics}` under `<workdir>/checkpoints/<epoch>`.

    Saving is synchronous and refuses a non-finite state: a checkpoint that `save` returned
    from is complete on disk, so a process killed at any later moment resumes from it. Its
    files' SHA-256 is recorded in `checkpoints/checksums.json`; `restore` verifies it, checks
    that the arrays it read are finite and, with `fall_back`, goes back to the newest
    checkpoint that passes both (with a warning). A checkpoint without a recorded checksum (a
    crash between its write and the record, or checksums.json lost) is said to be unverified,
    used if its arrays are finite, and recorded then. A damaged checksums.json verifies
    nothing: `restore` refuses (RunError naming it), and is never made to bless a checkpoint.
    """

    def __init__(self, directory: Path, max_to_keep: int = 3, *, create: bool = True):
        ocp = _orbax()
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=create,
                                               enable_async_checkpointing=False)
        self._directory = directory.absolute()
        self._manager = ocp.CheckpointManager(self._directory, options=options)
        self._checksums = self._directory / "checksums.json"

    @property
    def latest_epoch(self) -> int | None:
        return self._manager.latest_step()

    @property
    def directory(self) -> Path:
        return self._directory

    def save(self, epoch: int, state: Any, config: dict, records: list,
             progress: dict | None = None) -> None:
        """Save and checksum `epoch` (with `progress`: a checkpoint inside that epoch); a
        stop signal meanwhile takes effect once it is complete."""
        ocp = _orbax()
        if not _finite(state):
            raise RunError(f"refusing to save a non-finite training state (epoch {epoch})")
        items = dict(state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config),
                     metrics=ocp.args.JsonSave(records))
        if progress is not None:
            items["progress"] = ocp.args.JsonSave(progress)
        # After a failure the manager closes while stderr is held back and the writer threads'
        # reports are silenced, not at exit, where they printed "Event loop is closed"
        # tracebacks after the one-line error.
        with writes_completed(), _failures_quiet(then=self._manager.close):
            self._manager.save(epoch, args=ocp.args.Composite(**items))
            self._manager.wait_until_finished()
        self._record_checksum(epoch)

    def restore(self, like_state: Any, epoch: int | None = None, *,
                fall_back: bool = False) -> Restored:
        """Restore `epoch` (default: the latest); `like_state` (arrays or their abstract
        shapes) gives the tree structure and dtypes. With `fall_back`, a checkpoint that fails
        its checksum, cannot be read or holds non-finite arrays is skipped for the one before
        it. The arrays come back on this process's first device, whatever devices saved
        them."""
        here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        abstract = jax.tree.map(
            lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=here), like_state)
        candidates = [epoch] if epoch is not None else sorted(self._manager.all_steps(),
                                                              reverse=True)
        problems: list[str] = []
        for candidate in candidates:
            restored, problem = self._restore_verified(candidate, abstract)
            if restored is not None:                    # (the checkpoint, None)
                if problems:
                    warnings.warn(f"{self._directory}: using the checkpoint of epoch "
                                  f"{candidate}; skipped " + "; ".join(problems), stacklevel=2)
                return restored
            problems.append(f"epoch {candidate}: {problem}")
            if not fall_back:
                break
        raise RunError(f"no usable checkpoint in {self._directory}: " + "; ".join(problems)
                       if problems else f"no checkpoint in {self._directory}")

    def _restore_verified(self, epoch: int, abstract: Any) -> tuple[Restored | None, str | None]:
        """(the checkpoint, None), or (None, what is wrong with it)."""
        ocp = _orbax()
        expected = self._verifiable_checksums().get(str(epoch))
        if expected == UNVERIFIABLE:
            return None, (f"its checksum was lost ({self._checksums.name} was damaged before a "
                          "later checkpoint was saved), so it cannot be verified")
        if expected is not None and expected != self._checksum(epoch):
            return None, "its files do not match the checksum recorded when it was saved"
        items = dict(state=ocp.args.StandardRestore(abstract), config=ocp.args.JsonRestore(),
                     metrics=ocp.args.JsonRestore())
        if (self._directory / str(epoch) / "progress").is_dir():
            items["progress"] = ocp.args.JsonRestore()
        try:
            restored = self._manager.restore(epoch, args=ocp.args.Composite(**items))
        except Exception as error:  # orbax raises many kinds on damaged files
            return None, f"unreadable ({type(error).__name__})"
        if not _finite(restored.state):
            return None, "its arrays are not all finite"
        if expected is None:
            warnings.warn(f"{self._directory / str(epoch)} has no recorded checksum (a crash "
                          "right after it was written, or checksums.json lost), so it cannot be "
                          "verified; its arrays are finite and it is used (its checksum is "
                          "recorded now)", stacklevel=3)
            with contextlib.suppress(OSError):      # a read-only copy stays unrecorded
                self._record_checksum(epoch)
        progress = restored["progress"] if "progress" in items else None
        return Restored(restored.state, restored.config, list(restored.metrics), epoch,
                        progress), None

    def read_config(self, epoch: int | None = None) -> dict:
        """The JSON config stored with checkpoint `epoch`, by default the newest readable one
        (arrays untouched)."""
        return self.read_json("config", epoch)

    def read_json(self, item: str, epoch: int | None = None) -> Any:
        """A JSON item ("config", "metrics", "progress") of checkpoint `epoch`, by default
        the newest readable one (arrays untouched)."""
        ocp = _orbax()
        epochs = [epoch] if epoch is not None else sorted(self._manager.all_steps(), reverse=True)
        for epoch in epochs:
            try:
                return self._manager.restore(epoch, args=ocp.args.Composite(
                    **{item: ocp.args.JsonRestore()}))[item]
            except Exception:  # a damaged checkpoint: the one before it may do
                continue
        raise RunError(f"no readable checkpoint in {self._directory}")

    def discard_after(self, epoch: int) -> None:
        """Delete the checkpoints of later epochs (damaged ones that a resume skipped)."""
        for later in [e for e in self._manager.all_steps() if e > epoch]:
            self._manager.delete(later)

    def discard(self) -> None:
        """Delete every checkpoint (an interrupted epoch's, once a later one is saved)."""
        for epoch in self._manager.all_steps():
            self._manager.delete(epoch)
        if jax.process_index() == 0:
            self._checksums.unlink(missing_ok=True)

    def close(self) -> None:
        self._manager.close()

    def _checksum(self, epoch: int) -> str:
        digest = hashlib.sha256()
        folder = self._directory / str(epoch)
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
        return digest.hexdigest()

    def _read_checksums(self) -> dict | None:
        """The recorded checksums ({} before the first); None where checksums.json cannot be
        read or is not a record of them."""
        try:
            if self._checksums.exists() and not self._checksums.is_file():
                return None
            checksums = json.loads(self._checksums.read_text())
        except FileNotFoundError:
            return {}
        except (OSError, ValueError):
            return None
        valid = isinstance(checksums, dict) and all(
            isinstance(c, str) for c in checksums.values())
        return checksums if valid else None

    def _verifiable_checksums(self) -> dict:
        """The recorded checksums; RunError where checksums.json is damaged: then no
        checkpoint can be verified, and none is used or blessed."""
        checksums = self._read_checksums()
        if checksums is None:
            raise RunError(f"{self._checksums} is damaged, so no checkpoint of this run can be "
                           "verified and none is used: put back a good copy, or delete it to "
                           "use the checkpoints unverified (each then checked for finite "
                           "arrays only)")
        return checksums

    def _record_checksum(self, epoch: int) -> None:
        """Record `epoch`'s checksum, and drop those of checkpoints no longer kept. Where
        checksums.json is damaged, the other checkpoints are recorded as UNVERIFIABLE."""
        if jax.process_index() != 0:            # the checksums are written once
            return
        checksums = self._read_checksums()
        kept = {str(e) for e in self._manager.all_steps()}
        if checksums is None:
            warnings.warn(f"{self._checksums} was damaged: the checkpoints before epoch "
                          f"{epoch} can no longer be verified, and will not be used",
                          stacklevel=3)
            checksums = dict.fromkeys(kept, UNVERIFIABLE)
        checksums[str(epoch)] = self._checksum(epoch)
        write_atomically(self._checksums, json.dumps(
            {e: c for e, c in checksums.items() if e in kept}, indent=1))


# A checkpoint's entry in checksums.json once its recorded checksum was lost (the file was
# damaged when a later checkpoint was saved): it is never used.
UNVERIFIABLE = "unverifiable"


# The longest a failed save waits for the writer threads to finish reporting the failure,
# and how long nothing must have been written to the held stderr before it is given back.
WRITER_REPORTS_TIMEOUT_S = 5.0
WRITERS_QUIET_S = 1.0


def _join_started_since(threads_before: set[threading.Thread], timeout_s: float) -> None:
    """Wait, `timeout_s` at most in all, for the threads that are not in `threads_before`."""
    deadline = time.monotonic() + timeout_s
    for thread in set(threading.enumerate()) - threads_before:
        thread.join(max(0.0, deadline - time.monotonic()))


def _wait_until_quiet(held, quiet_s: float, timeout_s: float) -> None:
    """Wait until nothing has been written to `held` for `quiet_s` (`timeout_s` at most): a
    thread that ran before the save began (orbax's event loop) may still be mid-page."""
    deadline = time.monotonic() + timeout_s
    size, quiet_since = os.fstat(held.fileno()).st_size, time.monotonic()
    while time.monotonic() - quiet_since < quiet_s and time.monotonic() < deadline:
        time.sleep(0.05)
        if (grown := os.fstat(held.fileno()).st_size) != size:
            size, quiet_since = grown, time.monotonic()


@contextlib.contextmanager
def _failures_quiet(then: Callable[[], Any]) -> Iterator[None]:
    """A failed write (a full disk) is raised, once: orbax's and tensorstore's writer threads
    also print it, in pages of tracebacks on stderr during the save and from asyncio's tasks
    at exit. So stderr (the file descriptor, which C++ writes to as well) is held back during
    the save and replayed if it succeeds; after a failure their reports are silenced first,
    and only then is `then` called (closing the writers, whose threads fail on a closed event
    loop); stderr is given back once the threads started meanwhile have ended and nothing has
    been written for a second, so that a page still being written cannot land after the
    one-line error."""
    with tempfile.TemporaryFile() as held:
        sys.stderr.flush()
        stderr = os.dup(2)
        os.dup2(held.fileno(), 2)
        threads_before = set(threading.enumerate())
        try:
            yield
        except BaseException:
            for name in ("asyncio", "absl"):
                logging.getLogger(name).setLevel(logging.CRITICAL + 1)
            # Exceptions in threads, unraisable ones and coroutines never awaited: the
            # failure is already being reported.
            threading.excepthook = lambda *_: None
            sys.unraisablehook = lambda *_: None
            warnings.filterwarnings("ignore", "coroutine .* was never awaited", RuntimeWarning)
            with contextlib.suppress(Exception):
                then()
            _join_started_since(threads_before, timeout_s=WRITER_REPORTS_TIMEOUT_S)
            _wait_until_quiet(held, WRITERS_QUIET_S, timeout_s=WRITER_REPORTS_TIMEOUT_S)
            raise
        else:
            held.seek(0)
            os.write(stderr, held.read())
        finally:
            sys.stderr.flush()
            os.dup2(stderr, 2)
            os.close(stderr)


def _finite(tree: Any) -> bool:
    """Whether every floating-point array of `tree` is finite."""
    return all(bool(np.all(np.isfinite(leaf))) for leaf in jax.tree.leaves(tree)
               if np.issubdtype(leaf.dtype, np.floating))


def write_atomically(path: Path, text: str) -> None:
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)
