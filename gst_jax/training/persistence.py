"""What the epoch loop keeps on disk: its checkpoints, its metrics lines, and resuming from
them (`gst_jax.training.loop` trains).

A checkpoint every `checkpoint_every` epochs and at the end (checkpoints/), each with the
metrics records of every epoch so far, and one inside an epoch when a stop signal comes
(interrupted/, with what that epoch has summed so far, `EpochSoFar`, until a later save);
`resume` continues from the newer of the newest intact checkpoint and an interrupted epoch's,
of the same configuration (only the checkpoint cadence may change). A failed write (a full
disk) is one line that says what a rerun will do; a stop that ends the process early leaves
a note saying where it would continue.
"""

from __future__ import annotations

import dataclasses
import os
import re
import warnings
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from gst_jax.errors import RunError
from gst_jax.io.interrupts import set_forced_exit_note
from gst_jax.io.workdir import WorkDir, same_run
from gst_jax.progress import Progress
from gst_jax.training.state import TrainState


@dataclasses.dataclass
class EpochSoFar:
    """What an epoch has summed so far, saved with a checkpoint taken inside it."""

    steps_done: int
    loss_sum: np.ndarray                   # (members,) float64: loss x scenes
    non_finite: np.ndarray                 # (members,) int
    scenes: float = 0.0
    seconds: float = 0.0                   # of training, also before a resume
    compiles: int = 0
    compile_seconds: float = 0.0

    @classmethod
    def fresh(cls, members: int) -> "EpochSoFar":
        return cls(0, np.zeros(members), np.zeros(members, int))

    def to_json(self, epoch: int) -> dict:
        return {"epoch": epoch, **dataclasses.asdict(self), "loss_sum": self.loss_sum.tolist(),
                "non_finite": self.non_finite.tolist()}

    @classmethod
    def from_json(cls, record: dict) -> "EpochSoFar":
        fields = {k: v for k, v in record.items() if k != "epoch"}
        return cls(**{**fields, "loss_sum": np.array(fields["loss_sum"], np.float64),
                      "non_finite": np.array(fields["non_finite"], int)})


class Saves:
    """Where a training's state is saved: a checkpoint every `checkpoint_every` epochs
    (checkpoints/), and one inside an epoch when a stop signal comes (interrupted/, until a
    later save). It keeps the note that a stop ending the process early leaves, and turns a
    failed write (a full disk) into one line that says what the rerun will do."""

    def __init__(self, workdir: WorkDir, config: dict):
        self.workdir, self.config = workdir, config
        self.epochs = workdir.checkpointer()
        self.interrupted = workdir.interrupted_checkpointer()
        self.saved: str | None = None       # e.g. "epoch 5", "epoch 3 at step 7"

    def close(self) -> None:
        self.epochs.close()
        self.interrupted.close()

    @property
    def rerun(self) -> str:
        if self.saved is None:
            return f"rerunning the same command starts fresh in {self.workdir.path}"
        return f"rerunning the same command continues from {self.saved}"

    def noted(self, saved: str | None) -> None:
        self.saved = saved
        set_forced_exit_note(f"interrupted before the next save; {self.rerun}")

    def save_epoch(self, epoch: int, state: TrainState, records: list) -> None:
        self._write(lambda: self.epochs.save(epoch, state, self.config, records),
                    f"the checkpoint of epoch {epoch}", self.epochs.directory)
        if self.interrupted.latest_epoch is not None:
            self.interrupted.discard()
        self.noted(f"epoch {epoch}")

    def save_inside(self, epoch: int, so_far: EpochSoFar, state: TrainState,
                    records: list) -> None:
        """A checkpoint after `so_far.steps_done` steps of `epoch` (0: the epochs before it
        complete)."""
        def write():
            self.interrupted.discard()
            self.interrupted.save(epoch, state, self.config, records, so_far.to_json(epoch))
        self._write(write, f"the checkpoint inside epoch {epoch}", self.interrupted.directory)
        self.noted(f"epoch {epoch - 1}" if so_far.steps_done == 0
                   else f"epoch {epoch} at step {so_far.steps_done}")

    def append_metrics(self, record: dict) -> None:
        self._write(lambda: self.workdir.append_metrics(record), "a line of metrics.jsonl",
                    self.workdir.metrics_path)

    def write_metrics(self, records: list) -> None:
        self._write(lambda: self.workdir.write_metrics(records), "metrics.jsonl",
                    self.workdir.metrics_path)

    def _write(self, write: Callable[[], None], what: str, where: Path) -> None:
        try:
            write()
        except Exception as error:
            reason = _os_error_reason(error)
            if reason is None:
                raise
            raise RunError(f"could not write {what} to {where} ({reason}); nothing "
                           f"half-written is used: {self.rerun}") from None


def _os_error_reason(error: BaseException | None) -> str | None:
    """Why the system refused a write behind `error` ('No space left on device'), which orbax
    and tensorstore wrap in other exceptions (tensorstore names only its errno), or None."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, OSError):
            return error.strerror or str(error)
        if code := re.search(r"os_error_code='(\d+)'", str(error)):
            return os.strerror(int(code.group(1)))
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return None


def resume(init_state: Callable[[], TrainState], saves: Saves, config: dict, epochs: int,
           progress: Progress) -> tuple[TrainState, list, int, EpochSoFar | None]:
    """(state, records, epoch to start, what that epoch has done) from the newer of the
    newest intact checkpoint and an interrupted epoch's; a fresh state (`init_state()`) where
    there is none. config: the run's JSON config, which the checkpoints' must match."""
    like = jax.eval_shape(init_state)
    state, records, last_epoch, so_far = None, [], 0, None
    if saves.epochs.latest_epoch is not None:
        restored = saves.epochs.restore(like, fall_back=True)
        check_same_run(restored.config, config, saves.workdir)
        state, records, last_epoch = restored.state, restored.records, restored.epoch
        saves.epochs.discard_after(last_epoch)          # damaged ones that were skipped
        saves.noted(f"epoch {last_epoch}")
    if (saves.interrupted.latest_epoch or 0) > last_epoch:
        try:
            restored = saves.interrupted.restore(like)
        except RunError as error:
            warnings.warn(f"{error}; {saves.rerun}", stacklevel=2)
        else:
            check_same_run(restored.config, config, saves.workdir)
            state, records = restored.state, restored.records
            assert restored.progress is not None, "an interrupted epoch's save holds its progress"
            last_epoch, so_far = restored.epoch - 1, EpochSoFar.from_json(restored.progress)
            saves.noted(f"epoch {restored.epoch} at step {so_far.steps_done}"
                        if so_far.steps_done else f"epoch {last_epoch}")
    elif saves.interrupted.latest_epoch is not None:  # older than a checkpoint saved since
        saves.interrupted.discard()
    if state is None:
        progress.line(f"starting fresh: no checkpoint in {saves.workdir.path}")
        saves.noted(None)
        return init_state(), [], 1, None
    inside = so_far is not None and so_far.steps_done > 0       # saved: "epoch 3 at step 7"
    if last_epoch >= epochs and not inside:
        progress.line(f"already finished: {saves.workdir.path} holds all {epochs} epochs")
    else:
        progress.line(f"resuming {saves.workdir.path} {'from' if inside else 'after'} "
                      f"{saves.saved}")
    return state, records, last_epoch + 1, so_far


def check_same_run(stored_config: dict, config: dict, workdir: WorkDir) -> None:
    if not same_run(stored_config, config):
        raise RunError(f"the checkpoints in {workdir.path} belong to a run with a different "
                       "configuration; choose another --workdir or delete it")
