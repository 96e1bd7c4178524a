"""Training: one jitted `train_step`, an epoch loop with orbax checkpoints, metrics.jsonl.

`python -m gst_jax.train` with no arguments trains the paper's configuration (GST (D), n = 1,
ghost, seed 1000, 200 epochs, 16 scenes per step, Adam 1e-3 x 0.3 every 50 epochs, tau
annealed 0.5 -> 0.03, random rotation, dropout 0.1) on `eth` under the paper protocol.

Reproducibility: every random draw is a function of (seed, epoch, step), and checkpoints are
taken at epoch boundaries, so a run killed at any point and restarted with the same command
ends with exactly the parameters of an uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax

from gst_jax import augment, data, losses, rollout as rollout_lib
from gst_jax.checkpoints import Checkpointer
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.data import SceneBatch
from gst_jax.graph import drop_partially_detected
from gst_jax.model import init_params
from gst_jax.predict import make_predict


@flax.struct.dataclass
class TrainState:
    """Everything that changes during training. A pytree, so it can be jitted, vmapped, saved."""

    params: Any
    opt_state: Any
    step: jax.Array  # () int32, optimiser steps taken


@flax.struct.dataclass
class HParams:
    """Per-step hyperparameters, traced so that changing them never recompiles.

    Attributes: learning_rate (), tau () Gumbel temperature, num_edge_heads () int32 n
    (0 = full connection), ghost () bool, fully_detected_only () bool (the paper's "F"
    baseline: partially detected pedestrians are removed from the scene).
    """

    learning_rate: jax.Array
    tau: jax.Array
    num_edge_heads: jax.Array
    ghost: jax.Array
    fully_detected_only: jax.Array


def make_optimizer() -> optax.GradientTransformation:
    """Adam with the learning rate injected as state, so `HParams.learning_rate` drives it."""
    return optax.inject_hyperparams(optax.adam)(learning_rate=1e-3)


def create_train_state(model_config: ModelConfig, key: jax.Array) -> TrainState:
    params = init_params(model_config, key)
    return TrainState(params=params, opt_state=make_optimizer().init(params), step=jnp.int32(0))


def hparams_for_epoch(model_config: ModelConfig, train_config: TrainConfig, epoch: int,
                      fully_detected_only: bool | None = None) -> HParams:
    """Learning rate and temperature of a 1-based epoch, as in the release's schedule."""
    lr = train_config.learning_rate * train_config.lr_decay ** ((epoch - 1) // train_config.lr_decay_every)
    # The release anneals over its 200 epochs: tau(e) = (1 - e/E) (tau0 - tau1) + tau1.
    frac = epoch / train_config.epochs
    tau = (1.0 - frac) * (train_config.tau_start - train_config.tau_end) + train_config.tau_end
    if fully_detected_only is None:
        fully_detected_only = train_config.fully_detected_only
    return HParams(
        learning_rate=jnp.float32(lr),
        tau=jnp.float32(tau),
        num_edge_heads=jnp.int32(model_config.num_edge_heads),
        ghost=jnp.bool_(model_config.ghost),
        fully_detected_only=jnp.bool_(fully_detected_only),
    )


def batch_loss(params, model_config: ModelConfig, batch: SceneBatch, key: jax.Array,
               hparams: HParams, *, rotate: bool) -> jax.Array:
    """Mean over real scenes of the per-scene training loss (soft Gumbel samples, dropout on)."""
    rotate_key, rollout_key = jax.random.split(key)
    if rotate:
        batch = augment.rotate(rotate_key, batch)
    batch = drop_partially_detected(batch, hparams.fully_detected_only)
    controls = rollout_lib.Controls(tau=hparams.tau, num_edge_heads=hparams.num_edge_heads,
                                    ghost=hparams.ghost)
    output = rollout_lib.rollout(params, model_config, batch, rollout_key, controls,
                                 hard=False, deterministic=False)
    return losses.batch_loss(model_config, output, batch)


def make_train_step(model_config: ModelConfig, *, rotate: bool = True):
    """Build `train_step(state, key, batch, hparams) -> (state, metrics)`, not yet jitted.

    A step whose loss or gradients are not finite leaves the state unchanged and reports
    `finite = False`, so the caller can stop with the last good parameters.
    """
    optimizer = make_optimizer()

    def train_step(state: TrainState, key: jax.Array, batch: SceneBatch, hparams: HParams):
        loss, grads = jax.value_and_grad(batch_loss)(state.params, model_config, batch, key,
                                                     hparams, rotate=rotate)
        finite = jnp.isfinite(loss) & jnp.all(jnp.array(
            [jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grads)]))
        opt_state = state.opt_state._replace(
            hyperparams={**state.opt_state.hyperparams, "learning_rate": hparams.learning_rate})
        updates, new_opt_state = optimizer.update(grads, opt_state, state.params)
        new_state = TrainState(params=optax.apply_updates(state.params, updates),
                               opt_state=new_opt_state, step=state.step + 1)
        state = jax.tree.map(lambda new, old: jnp.where(finite, new, old), new_state, state)
        metrics = {"loss": loss, "finite": finite, "grad_norm": optax.tree.norm(grads)}
        return state, metrics

    return train_step


class NonFiniteError(RuntimeError):
    """Raised when a step's loss or gradients are not finite; the last checkpoint is kept."""


# Set by the crash-recovery test: the process SIGKILLs itself after this many optimiser steps.
_KILL_AFTER_STEPS_ENV = "GST_JAX_TEST_KILL_AFTER_STEPS"


def run_config(model_config: ModelConfig, data_config: DataConfig,
               train_config: TrainConfig) -> dict:
    """The JSON-serialisable description of a run, stored in the work dir and checkpoints."""
    return {"model": dataclasses.asdict(model_config), "data": dataclasses.asdict(data_config),
            "train": dataclasses.asdict(train_config)}


def load_train_set(data_config: DataConfig, train_config: TrainConfig):
    """The training windows, cut to the first `max_train_windows` when set (smoke tests)."""
    train_set = data.load_split(data_config, "train")
    if train_config.max_train_windows:
        train_set = train_set.subset(range(min(train_config.max_train_windows, len(train_set))))
    return train_set


def prepare_workdir(workdir: Path, config: dict) -> None:
    """Create the work dir, or check that an existing one belongs to the same run."""
    workdir.mkdir(parents=True, exist_ok=True)
    config_path = workdir / "config.json"
    if config_path.exists():
        existing = json.loads(config_path.read_text())
        if existing != config:
            raise SystemExit(
                f"{workdir} holds a run with a different configuration ({config_path}); "
                "choose another --workdir or delete it.")
    else:
        config_path.write_text(json.dumps(config, indent=2) + "\n")


def _truncate_metrics(metrics_path: Path, last_epoch: int) -> None:
    """Drop metric lines of epochs after the checkpoint we resume from (a killed run's tail)."""
    if not metrics_path.exists():
        return
    lines = [line for line in metrics_path.read_text().splitlines()
             if line.strip() and json.loads(line).get("epoch", 0) <= last_epoch]
    metrics_path.write_text("".join(line + "\n" for line in lines))


class _Progress:
    """One status line per epoch on any stream; a live line within the epoch on a terminal."""

    def __init__(self, stream=sys.stderr):
        self.stream = stream
        self.live = stream.isatty()

    def step(self, epoch: int, epochs: int, step: int, steps: int, scenes_per_s: float,
             loss: float, eta_s: float) -> None:
        if self.live:
            self.stream.write(f"\repoch {epoch}/{epochs} step {step}/{steps} "
                              f"{scenes_per_s:6.1f} scenes/s loss {loss:.4f} ETA {_hms(eta_s)}  ")
            self.stream.flush()

    def epoch(self, text: str) -> None:
        self.stream.write(("\r" if self.live else "") + text + "\n")
        self.stream.flush()


def _hms(seconds: float) -> str:
    seconds = int(max(seconds, 0))
    return f"{seconds // 3600:d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def fit(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
        workdir: str | Path, *, progress: _Progress | None = None) -> dict:
    """Train (or resume) a run in `workdir`; returns the summary also written to summary.json."""
    from gst_jax import evaluate  # evaluate imports train's state helpers; keep the cycle lazy

    workdir = Path(workdir)
    progress = progress or _Progress()
    config = run_config(model_config, data_config, train_config)
    prepare_workdir(workdir, config)
    metrics_path = workdir / "metrics.jsonl"

    train_set = load_train_set(data_config, train_config)
    has_val = data_config.protocol in ("paper-val", "loo")
    val_set = data.load_split(data_config, "val") if has_val else None
    # Built once: a fresh `make_predict` per validation would recompile every time.
    val_predict = make_predict(model_config, num_samples=1, with_graph=False) if has_val else None

    checkpointer = Checkpointer(workdir)
    base_key = jax.random.key(train_config.seed)
    # A key stream of its own (fold_in takes uint32 data, so no negative epochs).
    validation_key = jax.random.fold_in(base_key, 2 ** 32 - 1)
    state = create_train_state(model_config, jax.random.fold_in(base_key, 0))
    start_epoch = 1
    if checkpointer.latest_epoch is not None:
        state, _, last_epoch = checkpointer.restore(state)
        start_epoch = last_epoch + 1
        _truncate_metrics(metrics_path, last_epoch)
        progress.epoch(f"resuming {workdir} after epoch {last_epoch}")

    train_step = jax.jit(make_train_step(model_config, rotate=train_config.rotate),
                         donate_argnums=0)
    kill_after = int(os.environ.get(_KILL_AFTER_STEPS_ENV, "0"))
    steps_per_epoch = math.ceil(len(train_set) / train_config.batch_size)
    run_start = time.perf_counter()
    first_epoch_start = None
    for epoch in range(start_epoch, train_config.epochs + 1):
        hparams = hparams_for_epoch(model_config, train_config, epoch)
        epoch_key = jax.random.fold_in(base_key, epoch)
        epoch_start = time.perf_counter()
        first_epoch_start = first_epoch_start or epoch_start
        losses_sum, scenes = 0.0, 0
        batches = data.training_batches(train_set, batch_size=train_config.batch_size,
                                        seed=train_config.seed, epoch=epoch)
        for step, batch in enumerate(batches):
            state, metrics = train_step(state, jax.random.fold_in(epoch_key, step), batch, hparams)
            if not bool(metrics["finite"]):
                raise NonFiniteError(
                    f"non-finite loss or gradient at epoch {epoch}, batch {step} "
                    f"(loss {float(metrics['loss'])}); parameters of the last checkpoint "
                    f"(epoch {checkpointer.latest_epoch}) are kept in {workdir}/checkpoints")
            real = int(np.sum(batch.scene_mask))
            losses_sum += float(metrics["loss"]) * real
            scenes += real
            elapsed = time.perf_counter() - epoch_start
            done_steps = (epoch - start_epoch) * steps_per_epoch + step + 1
            total_steps = (train_config.epochs - start_epoch + 1) * steps_per_epoch
            rate = (time.perf_counter() - first_epoch_start) / done_steps
            progress.step(epoch, train_config.epochs, step + 1, steps_per_epoch,
                          scenes / max(elapsed, 1e-9), losses_sum / scenes,
                          rate * (total_steps - done_steps))
            if kill_after and int(state.step) >= kill_after:
                os.kill(os.getpid(), signal.SIGKILL)

        epoch_time = time.perf_counter() - epoch_start
        record = {"epoch": epoch, "loss": losses_sum / max(scenes, 1),
                  "tau": float(hparams.tau), "learning_rate": float(hparams.learning_rate),
                  "epoch_time_s": epoch_time, "scenes_per_s": scenes / epoch_time,
                  "step": int(state.step)}
        if val_set is not None and train_config.eval_every and (
                epoch % train_config.eval_every == 0 or epoch == train_config.epochs):
            val = evaluate.evaluate_params(
                state.params, model_config, val_set, jax.random.fold_in(validation_key, epoch),
                num_samples=1, fully_detected_only=train_config.fully_detected_only,
                predict=val_predict)
            record.update(val_aoe=val["aoe"], val_foe=val["foe"])
        if epoch % train_config.checkpoint_every == 0 or epoch == train_config.epochs:
            checkpointer.save(epoch, state, config)
        with metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        progress.epoch(" ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                for k, v in record.items()))

    checkpointer.close()
    summary = {"workdir": str(workdir), "epochs": train_config.epochs,
               "final_loss": _last_metric(metrics_path, "loss"),
               "wall_time_s": time.perf_counter() - run_start,
               "train_windows": len(train_set), "config": config}
    (workdir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def training_time_s(workdir: str | Path) -> float:
    """Sum of the epoch times in metrics.jsonl: the training's wall time across resumes."""
    lines = (Path(workdir) / "metrics.jsonl").read_text().splitlines()
    return sum(json.loads(line).get("epoch_time_s", 0.0) for line in lines)


def _last_metric(metrics_path: Path, name: str):
    lines = metrics_path.read_text().splitlines() if metrics_path.exists() else []
    return json.loads(lines[-1]).get(name) if lines else None


def main(argv: list[str] | None = None) -> None:
    import argparse

    from gst_jax import cli

    parser = argparse.ArgumentParser(
        prog="python -m gst_jax.train", description=__doc__.split("\n\n")[0])
    cli.add_data_flags(parser)
    cli.add_model_flags(parser)
    cli.add_train_flags(parser)
    cli.add_output_flags(parser, workdir_help="where checkpoints, metrics.jsonl and summary.json "
                         "go; rerunning the same command resumes there "
                         "(default: runs/<scene>-<protocol>-<d|p>-n<n>-e<epochs>-seed<seed>)")
    args = parser.parse_args(argv)
    data_config, model_config, train_config = (cli.data_config(args), cli.model_config(args),
                                               cli.train_config(args))
    workdir = Path(args.workdir or Path("runs") / cli.run_name(data_config, model_config,
                                                                train_config))
    print(f"work directory: {workdir}", file=sys.stderr)
    try:
        summary = fit(model_config, data_config, train_config, workdir)
    except NonFiniteError as error:
        raise SystemExit(f"error: {error}")
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"trained {summary['epochs']} epochs on {summary['train_windows']} windows in "
              f"{summary['wall_time_s']:.0f} s; final loss {summary['final_loss']:.4f}; "
              f"evaluate with: python -m gst_jax.evaluate {workdir}")


if __name__ == "__main__":
    main()
