"""The epoch loop, written once for single runs and sweeps, and `fit`, which trains one run.

The loop resumes from the newest intact checkpoint (of the same configuration; only the
checkpoint cadence may change), saves a checkpoint every `checkpoint_every` epochs and at the
end, each with the metrics records of every epoch so far, writes one metrics.jsonl line per
epoch (rewritten from the checkpoint on resume, so a kill at any moment leaves one line per
completed epoch), shows progress with an ETA, and applies the non-finite policy: a step whose
loss, gradients or new state are not finite keeps the state it had (`make_train_step` does
that); a single run then stops with `NonFiniteError`, a sweep counts it per member and goes on.
The checkpoints, the metrics lines and the resume are `gst_jax.training.persistence`'s; a
fine-tuning's choice of epoch on validation is `gst_jax.training.selection`'s.

`python -m gst_jax.train` with no arguments trains the paper's configuration (GST (D), n = 1,
ghost, seed 1000, 200 epochs, 16 scenes per step, Adam 1e-3 x 0.3 every 50 epochs, tau
annealed 0.5 -> 0.03, random rotation, dropout 0.1) on `eth` under the paper protocol.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
import warnings
from functools import partial
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax import data
from gst_jax.compiles import count_compiles
from gst_jax.config import DataConfig, ModelConfig, TimeGrid, TrainConfig
from gst_jax.errors import DataError, Interrupted, NonFiniteError
from gst_jax.evaluation import evaluate_params
from gst_jax.io.interrupts import stop_requested, stops_noted
from gst_jax.io.workdir import WorkDir, code_version, run_config, same_run
from gst_jax.parallel import Devices
from gst_jax.predict import make_predict
from gst_jax.progress import Progress, StepClock
from gst_jax.runs import load_model
from gst_jax.training.persistence import EpochSoFar, Saves, resume
from gst_jax.training.selection import Selection, check_same_layout, fine_tuning_state
from gst_jax.training.state import (
    HParams,
    TrainState,
    create_train_state,
    hparams_for_epoch,
    parameter_key,
    step_key,
    validation_key,
)
from gst_jax.training.step import TrainStep, make_train_step


@dataclasses.dataclass(frozen=True)
class Training:
    """What the loop trains: one run, or the members of a sweep stacked on a leading axis.

    Attributes:
      init_state: () -> a fresh state; called only when there is no checkpoint to resume.
      train_step: a `TrainStep`: (state, key, packed step, hparams) -> (state, metrics); for
        a sweep every argument but the packed step carries the member axis. Its devices
        are those the loop trains on.
      hparams: epoch -> HParams (stacked for a sweep).
      seeds: one per member (one for a single run); they derive the step keys.
      member_names: None for a single run (unstacked state, scalar metrics).
    """

    init_state: Callable[[], TrainState]
    train_step: TrainStep
    hparams: Callable[[int], HParams]
    seeds: tuple[int, ...]
    member_names: tuple[str, ...] | None = None

    def step_keys(self, epoch: int, step: int) -> jax.Array:
        keys = [step_key(seed, epoch, step) for seed in self.seeds]
        return keys[0] if self.member_names is None else jnp.stack(keys)

    def per_member(self, values: np.ndarray) -> Any:
        """A float for a single run, {member name: float} for a sweep."""
        if self.member_names is None:
            return float(values[0])
        return {name: float(v) for name, v in zip(self.member_names, values)}


def train_epochs(training: Training, workdir: WorkDir, config: dict, train_set: data.WindowSet,
                 train_config: TrainConfig, *, stop_on_non_finite: bool,
                 after_epoch: Callable[[int, TrainState], dict] | None = None,
                 progress: Progress | None = None) -> tuple[TrainState, list[dict]]:
    """Train (or resume) up to `train_config.epochs`; returns the final state and the metrics
    records of every epoch.

    config: the run's JSON config, stored with every checkpoint. after_epoch: extra fields
    of an epoch's metrics record (validation), given the epoch and its final state. A stop
    signal (Ctrl-C, SIGTERM) ends it after the step under way: the state there is saved, and
    `Interrupted` says what a rerun continues from.
    """
    progress = progress or Progress()
    with stops_noted(), contextlib.closing(Saves(workdir, config)) as saves:
        state, records, start_epoch, so_far = resume(training.init_state, saves, config,
                                                     train_config.epochs, progress)
        # One line per epoch up to the checkpoint, each saved with it: what a killed run wrote
        # after the checkpoint goes, what it did not get to write comes back.
        saves.write_metrics(records)
        train_step = training.train_step
        state = train_step.place(state)

        steps_per_epoch = math.ceil(len(train_set) / train_config.batch_size)
        first_step = so_far.steps_done if so_far else 0
        total_steps = (train_config.epochs - start_epoch + 1) * steps_per_epoch - first_step
        members = len(training.seeds)
        clock, compile_seconds = StepClock(), 0.0  # compile_seconds: those of earlier epochs

        unsaved = False                 # steps taken since the last save (or the resume)

        def stop_if_requested(epoch: int, epoch_so_far: EpochSoFar) -> None:
            signal_name = stop_requested()
            if signal_name is None:
                return
            if unsaved:
                saves.save_inside(epoch, epoch_so_far, state, records)
            raise Interrupted(f"interrupted ({signal_name}): {saves.rerun}")

        for epoch in range(start_epoch, train_config.epochs + 1):
            epoch_so_far = so_far if epoch == start_epoch and so_far else (
                EpochSoFar.fresh(members))
            stop_if_requested(epoch, epoch_so_far)
            hparams = train_step.place(training.hparams(epoch))
            resumed_at = time.perf_counter() - epoch_so_far.seconds
            steps = data.training_batches(train_set, batch_size=train_config.batch_size,
                                          seed=train_config.seed, epoch=epoch,
                                          slots_multiple=train_step.slots_multiple,
                                          one_micro_batch=train_step.one_micro_batch,
                                          first_step=epoch_so_far.steps_done)
            with count_compiles() as compiles:
                for step, packed in enumerate(steps, start=epoch_so_far.steps_done):
                    keys = train_step.place(training.step_keys(epoch, step))
                    state, metrics = train_step(state, keys, packed, hparams)
                    loss = np.atleast_1d(np.asarray(metrics["loss"], np.float64))
                    finite = np.atleast_1d(np.asarray(metrics["finite"]))
                    if stop_on_non_finite and not finite.all():
                        raise NonFiniteError(
                            f"non-finite loss or gradient at epoch {epoch}, batch {step} "
                            f"(loss {loss[0]}); parameters of the last checkpoint (epoch "
                            f"{saves.epochs.latest_epoch}) are kept in "
                            f"{workdir.path}/checkpoints")
                    epoch_so_far.loss_sum += (np.where(np.isfinite(loss), loss, 0.0)
                                              * packed.num_scenes)
                    epoch_so_far.non_finite += ~finite
                    epoch_so_far.scenes += packed.num_scenes
                    epoch_so_far.steps_done = step + 1
                    epoch_so_far.seconds = time.perf_counter() - resumed_at
                    unsaved = True
                    done = (epoch - start_epoch) * steps_per_epoch + step + 1 - first_step
                    eta = clock.eta(done, total_steps - done, compile_seconds + compiles.seconds)
                    progress.live(
                        f"epoch {epoch}/{train_config.epochs} step {step + 1}/{steps_per_epoch} "
                        f"{epoch_so_far.scenes / max(epoch_so_far.seconds, 1e-9):6.1f} scenes/s "
                        f"loss {float(np.mean(epoch_so_far.loss_sum)) / epoch_so_far.scenes:.4f} "
                        f"ETA {eta}")
                    if stop_requested() and step + 1 < steps_per_epoch:   # else at its end
                        epoch_so_far.compiles += compiles.count
                        epoch_so_far.compile_seconds += compiles.seconds
                        stop_if_requested(epoch, epoch_so_far)

            epoch_time = time.perf_counter() - resumed_at
            compile_seconds += compiles.seconds
            scenes = max(epoch_so_far.scenes, 1.0)
            record = {"epoch": epoch, "loss": training.per_member(epoch_so_far.loss_sum / scenes),
                      "tau": float(np.ravel(hparams.controls.tau)[0]),
                      "learning_rate": float(np.ravel(hparams.learning_rate)[0]),
                      "epoch_time_s": epoch_time, "scenes_per_s": epoch_so_far.scenes / epoch_time,
                      "step": int(np.max(state.step)),
                      "compiles": epoch_so_far.compiles + compiles.count,
                      "compile_time_s": epoch_so_far.compile_seconds + compiles.seconds,
                      "code": code_version()}
            if epoch_so_far.non_finite.any():
                names = training.member_names or ("run",)
                record["non_finite_steps"] = {name: int(v) for name, v
                                              in zip(names, epoch_so_far.non_finite) if v}
            if after_epoch is not None:
                record.update(after_epoch(epoch, state))
            # Wall-clock time, so that a log shows time spent between epochs (a stall, a slow
            # checkpoint) that epoch_time_s does not.
            record["finished_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            records.append(record)
            if epoch % train_config.checkpoint_every == 0 or epoch == train_config.epochs:
                saves.save_epoch(epoch, state, records)
                unsaved = False
            saves.append_metrics(record)
            progress.line(_format_record(record))
        if saves.interrupted.latest_epoch is not None:     # the run ended after it
            saves.interrupted.discard()
    workdir.tidy()
    return state, records


def _format_record(record: dict) -> str:
    """`epoch 3 loss 0.4 ...`; a sweep's per-member values as their range."""
    def value(v):
        if isinstance(v, dict):
            return f"{min(v.values()):.4g}..{max(v.values()):.4g}" if v else "-"
        return f"{v:.4g}" if isinstance(v, float) else str(v)
    return " ".join(f"{name} {value(v)}" for name, v in record.items())


def load_train_set(data_config: DataConfig, train_config: TrainConfig,
                   grid: TimeGrid) -> data.WindowSet:
    """The training windows on the model's time grid, cut to the first `max_train_windows`
    when set (smoke tests)."""
    train_set = data.load_split(data_config, "train", grid)
    if train_config.max_train_windows:
        train_set = train_set.subset(range(min(train_config.max_train_windows, len(train_set))))
    if not len(train_set):
        raise DataError(data.no_windows_message(train_set, data_config, "train", grid))
    return train_set


def fit(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
        workdir: str | Path | WorkDir, *, progress: Progress | None = None,
        devices: Devices | None = None) -> dict:
    """Train (or resume) one run in `workdir`; returns the summary also written there.
    devices: each step's scenes are split over them (`gst_jax.parallel`). A fine-tuning
    (`train_config.init`) with a validation split selects its epoch there (`Selection`) and
    reports the selected model beside the one it started from and constant velocity on the
    test windows."""
    workdir = workdir if isinstance(workdir, WorkDir) else WorkDir(workdir)
    train_set = load_train_set(data_config, train_config, model_config.grid)
    seed = train_config.seed
    source = None
    if train_config.init:
        source = load_model(train_config.init)
        check_same_layout(model_config, source)
        init_state = partial(fine_tuning_state, source)
    else:
        init_state = partial(create_train_state, model_config, parameter_key(seed))
    config = run_config(model_config, data_config, train_config)
    training = Training(
        init_state=init_state,
        train_step=make_train_step(model_config, rotate=train_config.rotate, devices=devices),
        hparams=lambda epoch: hparams_for_epoch(model_config, train_config, epoch),
        seeds=(seed,))
    after_epoch = _validation(model_config, data_config, train_config, devices)
    selection = None
    if source is not None and data.has_validation(data_config):
        selection = Selection(model_config, data_config, train_config, workdir, config, devices)
        after_epoch = selection.after_epoch
    elif source is not None:
        warnings.warn(f"protocol {data_config.protocol!r} has no validation split, so the "
                      "fine-tuning keeps its last epoch, however it does; --protocol paper-val "
                      "selects the epoch on windows held out of the training data",
                      stacklevel=2)
    start = time.perf_counter()
    with workdir.lock():
        workdir.prepare(config)
        finished = workdir.read_summary()
        if finished is not None and same_run(finished["config"], config):
            workdir.tidy()                  # made before finished trainings tidied up
            (progress or Progress()).line(
                f"already finished: {workdir.path} holds all {train_config.epochs} epochs; "
                f"its summary is {workdir.path / 'summary.json'}")
            return {**finished, "already_finished": True}
        if selection is not None:
            selection.start(init_state)
        state, records = train_epochs(
            training, workdir, config, train_set, train_config, stop_on_non_finite=True,
            after_epoch=after_epoch, progress=progress)
        summary = {"workdir": str(workdir.path), "epochs": train_config.epochs,
                   "final_loss": records[-1]["loss"],
                   "wall_time_s": time.perf_counter() - start, "train_windows": len(train_set),
                   "config": config}
        if selection is not None and source is not None:        # a selection has a source
            summary["fine_tuning"] = selection.report(source, state, data_config)
        workdir.write_summary(summary)
    return summary


def _validation(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
                devices: Devices | None) -> Callable[[int, TrainState], dict] | None:
    """Validation AOE/FOE (one sample) every `eval_every` epochs and at the last, where the
    protocol has a validation split."""
    if not (data.has_validation(data_config) and train_config.eval_every):
        return None
    val_set = data.load_split(data_config, "val", model_config.grid)
    # Built once: a fresh `make_predict` per validation would recompile every time.
    predict = make_predict(model_config, num_samples=1, with_graph=False)

    def validate(epoch: int, state: TrainState) -> dict:
        if epoch % train_config.eval_every and epoch != train_config.epochs:
            return {}
        result = evaluate_params(state.params, validation_key(train_config.seed, epoch), val_set,
                                 model_config, num_samples=1, predict=predict,
                                 fully_detected_only=train_config.fully_detected_only,
                                 devices=devices)
        return {"val_aoe": result["aoe"], "val_foe": result["foe"]}

    return validate
