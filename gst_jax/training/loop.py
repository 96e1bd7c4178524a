"""The epoch loop, written once for single runs and sweeps, and `fit`, which trains one run.

The loop resumes from the newest intact checkpoint (of the same configuration; only the
checkpoint cadence may change), saves a checkpoint every `checkpoint_every` epochs and at the
end, each with the metrics records of every epoch so far, writes one metrics.jsonl line per
epoch (rewritten from the checkpoint on resume, so a kill at any moment leaves one line per
completed epoch), shows progress with an ETA, and applies the non-finite policy: a step whose
loss, gradients or new state are not finite keeps the state it had (`make_train_step` does
that); a single run then stops with `NonFiniteError`, a sweep counts it per member and goes on.

`python -m gst_jax.train` with no arguments trains the paper's configuration (GST (D), n = 1,
ghost, seed 1000, 200 epochs, 16 scenes per step, Adam 1e-3 x 0.3 every 50 epochs, tau
annealed 0.5 -> 0.03, random rotation, dropout 0.1) on `eth` under the paper protocol.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax import data
from gst_jax.compiles import count_compiles
from gst_jax.config import DataConfig, ModelConfig, TimeGrid, TrainConfig
from gst_jax.errors import DataError, NonFiniteError, RunError
from gst_jax.evaluation import evaluate_params
from gst_jax.io.interrupts import interrupts_noticed
from gst_jax.io.workdir import WorkDir, code_version, run_config, same_run
from gst_jax.parallel import Devices
from gst_jax.predict import make_predict
from gst_jax.progress import Progress, StepClock
from gst_jax.runs import Run, load_model
from gst_jax.training.state import (HParams, TrainState, abstract_train_state, create_train_state,
                                    hparams_for_epoch, make_optimizer, parameter_key, step_key,
                                    validation_key)
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
    of an epoch's metrics record (validation), given the epoch and its final state.
    """
    progress = progress or Progress()
    checkpointer = workdir.checkpointer()
    if checkpointer.latest_epoch is None:
        state, records, last_epoch = training.init_state(), [], 0
    else:
        state, stored_config, records, last_epoch = checkpointer.restore(
            jax.eval_shape(training.init_state), fall_back=True)
        if not same_run(stored_config, config):
            raise RunError(f"the checkpoints in {workdir.path} belong to a run with a different "
                           "configuration; choose another --workdir or delete it")
        checkpointer.discard_after(last_epoch)          # damaged ones that were skipped
        progress.line(f"resuming {workdir.path} after epoch {last_epoch}")
    # One line per epoch up to the checkpoint, each saved with it: what a killed run wrote
    # after the checkpoint goes, what it did not get to write comes back.
    workdir.write_metrics(records)
    start_epoch = last_epoch + 1
    train_step = training.train_step
    state = train_step.place(state)

    steps_per_epoch = math.ceil(len(train_set) / train_config.batch_size)
    total_steps = (train_config.epochs - start_epoch + 1) * steps_per_epoch
    members = len(training.seeds)
    clock, compile_seconds = StepClock(), 0.0  # compile_seconds: those of earlier epochs
    with interrupts_noticed() as check_interrupt, contextlib.closing(checkpointer):
        for epoch in range(start_epoch, train_config.epochs + 1):
            hparams = train_step.place(training.hparams(epoch))
            epoch_start = time.perf_counter()
            loss_sum, non_finite, scenes = np.zeros(members), np.zeros(members, int), 0.0
            steps = data.training_batches(train_set, batch_size=train_config.batch_size,
                                          seed=train_config.seed, epoch=epoch,
                                          slots_multiple=train_step.slots_multiple,
                                          one_micro_batch=train_step.one_micro_batch)
            with count_compiles() as compiles:
                for step, packed in enumerate(steps):
                    keys = train_step.place(training.step_keys(epoch, step))
                    state, metrics = train_step(state, keys, packed, hparams)
                    loss = np.atleast_1d(np.asarray(metrics["loss"], np.float64))
                    finite = np.atleast_1d(np.asarray(metrics["finite"]))
                    if stop_on_non_finite and not finite.all():
                        raise NonFiniteError(
                            f"non-finite loss or gradient at epoch {epoch}, batch {step} "
                            f"(loss {loss[0]}); parameters of the last checkpoint (epoch "
                            f"{checkpointer.latest_epoch}) are kept in "
                            f"{workdir.path}/checkpoints")
                    loss_sum += np.where(np.isfinite(loss), loss, 0.0) * packed.num_scenes
                    non_finite += ~finite
                    scenes += packed.num_scenes
                    done = (epoch - start_epoch) * steps_per_epoch + step + 1
                    eta = clock.eta(done, total_steps - done, compile_seconds + compiles.seconds)
                    progress.live(
                        f"epoch {epoch}/{train_config.epochs} step {step + 1}/{steps_per_epoch} "
                        f"{scenes / max(time.perf_counter() - epoch_start, 1e-9):6.1f} scenes/s "
                        f"loss {float(np.mean(loss_sum)) / scenes:.4f} "
                        f"ETA {eta}")
                    check_interrupt()

            epoch_time = time.perf_counter() - epoch_start
            compile_seconds += compiles.seconds
            record = {"epoch": epoch, "loss": training.per_member(loss_sum / max(scenes, 1.0)),
                      "tau": float(np.ravel(hparams.controls.tau)[0]),
                      "learning_rate": float(np.ravel(hparams.learning_rate)[0]),
                      "epoch_time_s": epoch_time, "scenes_per_s": scenes / epoch_time,
                      "step": int(np.max(state.step)), "compiles": compiles.count,
                      "compile_time_s": compiles.seconds, "code": code_version()}
            if non_finite.any():
                names = training.member_names or ("run",)
                record["non_finite_steps"] = {name: int(v) for name, v in zip(names, non_finite)
                                              if v}
            if after_epoch is not None:
                record.update(after_epoch(epoch, state))
            # Wall-clock time, so that a log shows time spent between epochs (a stall, a slow
            # checkpoint) that epoch_time_s does not.
            record["finished_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            records.append(record)
            if epoch % train_config.checkpoint_every == 0 or epoch == train_config.epochs:
                checkpointer.save(epoch, state, config, records)
            workdir.append_metrics(record)
            progress.line(_format_record(record))
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
        files = ", ".join(path for path, _ in train_set.files) or "no files"
        raise DataError(f"no training windows in {data_config.scene} ({data_config.protocol} "
                             f"protocol): none of {files} gives one")
    return train_set


def fit(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
        workdir: str | WorkDir, *, progress: Progress | None = None,
        devices: Devices | None = None) -> dict:
    """Train (or resume) one run in `workdir`; returns the summary also written there.
    devices: each step's scenes are split over them (`gst_jax.parallel`)."""
    workdir = workdir if isinstance(workdir, WorkDir) else WorkDir(workdir)
    train_set = load_train_set(data_config, train_config, model_config.grid)
    seed = train_config.seed
    if train_config.init:
        source = load_model(train_config.init)
        check_same_layout(model_config, source)
        init_state = partial(fine_tuning_state, source)
    else:
        init_state = partial(create_train_state, model_config, parameter_key(seed))
    config = run_config(model_config, data_config, train_config)
    workdir.prepare(config)
    training = Training(
        init_state=init_state,
        train_step=make_train_step(model_config, rotate=train_config.rotate, devices=devices),
        hparams=lambda epoch: hparams_for_epoch(model_config, train_config, epoch),
        seeds=(seed,))
    start = time.perf_counter()
    _, records = train_epochs(
        training, workdir, config, train_set, train_config, stop_on_non_finite=True,
        after_epoch=_validation(model_config, data_config, train_config, devices),
        progress=progress)
    summary = {"workdir": str(workdir.path), "epochs": train_config.epochs,
               "final_loss": records[-1]["loss"],
               "wall_time_s": time.perf_counter() - start, "train_windows": len(train_set),
               "config": config}
    workdir.write_summary(summary)
    return summary


def fine_tuning_state(source: Run) -> TrainState:
    """A fresh optimiser on the parameters of `source` (fine-tuning)."""
    return TrainState(params=source.params, opt_state=make_optimizer().init(source.params),
                      step=jnp.int32(0))


def check_same_layout(model_config: ModelConfig, source: Run) -> None:
    """Refuse to fine-tune `source` as `model_config` unless their parameters have the same
    arrays (path and shape), as a resume would."""
    expected = jax.tree_util.tree_flatten_with_path(abstract_train_state(model_config).params)[0]
    given = jax.tree_util.tree_flatten_with_path(source.params)[0]
    layout = {jax.tree_util.keystr(path): tuple(leaf.shape) for path, leaf in expected}
    theirs = {jax.tree_util.keystr(path): tuple(leaf.shape) for path, leaf in given}
    if layout != theirs:
        different = sorted(k for k in layout.keys() | theirs.keys()
                           if layout.get(k) != theirs.get(k))
        raise RunError(f"{source.name} has another architecture than this run (e.g. "
                       f"{different[0]}: {theirs.get(different[0])} against "
                       f"{layout.get(different[0])}); fine-tune a model of the same shapes")


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
