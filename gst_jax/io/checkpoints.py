"""Checkpoints of a training state: orbax, checksummed, restored with a fall-back."""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

from gst_jax.errors import RunError
from gst_jax.io.interrupts import interrupts_deferred


class Restored(NamedTuple):
    """A checkpoint read back: the state, the run's config, the metrics records up to its
    epoch (one per epoch), and the epoch."""

    state: Any
    config: dict
    records: list
    epoch: int


class Checkpointer:
    """Saves `{state, config, metrics}` under `<workdir>/checkpoints/<epoch>`.

    Saving is synchronous and refuses a non-finite state: a checkpoint that `save` returned
    from is complete on disk, so a process killed at any later moment resumes from it. Its
    files' SHA-256 is recorded in `checkpoints/checksums.json`; `restore` verifies it and,
    with `fall_back`, goes back to the newest checkpoint that is intact (with a warning).
    """

    def __init__(self, directory: Path, max_to_keep: int = 3, *, create: bool = True):
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=create,
                                               enable_async_checkpointing=False)
        self._directory = directory.absolute()
        self._manager = ocp.CheckpointManager(self._directory, options=options)
        self._checksums = self._directory / "checksums.json"

    @property
    def latest_epoch(self) -> int | None:
        return self._manager.latest_step()

    def save(self, epoch: int, state: Any, config: dict, records: list) -> None:
        """Save and checksum `epoch`; a Ctrl-C meanwhile takes effect once it is complete."""
        if not all(bool(np.all(np.isfinite(leaf))) for leaf in jax.tree.leaves(state)
                   if np.issubdtype(leaf.dtype, np.floating)):
            raise RunError(f"refusing to save a non-finite training state (epoch {epoch})")
        with interrupts_deferred():
            self._manager.save(epoch, args=ocp.args.Composite(
                state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config),
                metrics=ocp.args.JsonSave(records)))
            self._manager.wait_until_finished()
            if jax.process_index() != 0:            # the checksums are written once
                return
            checksums = self._read_checksums()
            checksums[str(epoch)] = self._checksum(epoch)
            kept = {str(e) for e in self._manager.all_steps()}
            write_atomically(self._checksums, json.dumps(
                {e: c for e, c in checksums.items() if e in kept}, indent=1))

    def restore(self, like_state: Any, epoch: int | None = None, *,
                fall_back: bool = False) -> Restored:
        """Restore `epoch` (default: the latest); `like_state` (arrays or their abstract
        shapes) gives the tree structure and dtypes. With `fall_back`, a checkpoint that fails
        its checksum or cannot be read is skipped for the one before it. The arrays come back
        on this process's first device, whatever devices saved them."""
        here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        abstract = jax.tree.map(
            lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=here), like_state)
        candidates = [epoch] if epoch is not None else sorted(self._manager.all_steps(),
                                                              reverse=True)
        problems = []
        for candidate in candidates:
            problem = self._verify(candidate)
            if problem is None:
                try:
                    restored = self._manager.restore(candidate, args=ocp.args.Composite(
                        state=ocp.args.StandardRestore(abstract), config=ocp.args.JsonRestore(),
                        metrics=ocp.args.JsonRestore()))
                except Exception as error:  # orbax raises many kinds on damaged files
                    problem = f"unreadable ({type(error).__name__})"
            if problem is None:
                if problems:
                    warnings.warn(f"{self._directory}: using the checkpoint of epoch "
                                  f"{candidate}; skipped " + "; ".join(problems), stacklevel=2)
                return Restored(restored.state, restored.config, list(restored.metrics),
                                candidate)
            problems.append(f"epoch {candidate}: {problem}")
            if not fall_back:
                break
        raise RunError(f"no usable checkpoint in {self._directory}: " + "; ".join(problems)
                       if problems else f"no checkpoint in {self._directory}")

    def read_config(self, epoch: int | None = None) -> dict:
        """The JSON config stored with checkpoint `epoch`, by default the newest readable one
        (arrays untouched)."""
        epochs = [epoch] if epoch is not None else sorted(self._manager.all_steps(), reverse=True)
        for epoch in epochs:
            try:
                return self._manager.restore(epoch, args=ocp.args.Composite(
                    config=ocp.args.JsonRestore())).config
            except Exception:  # a damaged checkpoint: the one before it may do
                continue
        raise RunError(f"no readable checkpoint in {self._directory}")

    def discard_after(self, epoch: int) -> None:
        """Delete the checkpoints of later epochs (damaged ones that a resume skipped)."""
        for later in [e for e in self._manager.all_steps() if e > epoch]:
            self._manager.delete(later)

    def close(self) -> None:
        self._manager.close()

    def _checksum(self, epoch: int) -> str:
        digest = hashlib.sha256()
        folder = self._directory / str(epoch)
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
        return digest.hexdigest()

    def _read_checksums(self) -> dict:
        try:
            return json.loads(self._checksums.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def _verify(self, epoch: int) -> str | None:
        """None if the checkpoint's files match the checksum recorded when it was saved (or
        none was recorded: a crash between the save and the record); else the problem."""
        expected = self._read_checksums().get(str(epoch))
        if expected is not None and expected != self._checksum(epoch):
            return "its files do not match the checksum recorded when it was saved"
        return None


def write_atomically(path: Path, text: str) -> None:
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)
