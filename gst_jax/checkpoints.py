"""orbax checkpoints of a training state plus the JSON config of the run that made it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp


class Checkpointer:
    """Saves `{state, config}` under `<workdir>/checkpoints/<epoch>`; restores the latest.

    Saving is synchronous: a checkpoint that `save` returned from is complete on disk, so a
    process killed at any later moment resumes from it.
    """

    def __init__(self, workdir: str | Path, max_to_keep: int = 3):
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep,
                                               enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(Path(workdir).absolute() / "checkpoints",
                                              options=options)

    @property
    def latest_epoch(self) -> int | None:
        return self._manager.latest_step()

    def save(self, epoch: int, state: Any, config: dict) -> None:
        self._manager.save(epoch, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config)))
        self._manager.wait_until_finished()

    def restore(self, like_state: Any, epoch: int | None = None) -> tuple[Any, dict, int]:
        """Restore `(state, config, epoch)`; `like_state` gives the tree structure and dtypes."""
        epoch = self.latest_epoch if epoch is None else epoch
        if epoch is None:
            raise FileNotFoundError(f"no checkpoint under {self._manager.directory}")
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like_state)
        restored = self._manager.restore(epoch, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), config=ocp.args.JsonRestore()))
        return restored.state, restored.config, epoch

    def read_config(self, epoch: int | None = None) -> dict:
        """The JSON config stored with a checkpoint, without touching the arrays."""
        epoch = self.latest_epoch if epoch is None else epoch
        if epoch is None:
            raise FileNotFoundError(f"no checkpoint under {self._manager.directory}")
        return self._manager.restore(epoch, args=ocp.args.Composite(
            config=ocp.args.JsonRestore())).config

    def close(self) -> None:
        self._manager.close()
