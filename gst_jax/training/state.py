"""Training state, per-epoch hyperparameters, optimiser, schedule and keys (docs/MODEL.md 3).

Every random draw of a training is a function of (seed, epoch, step): parameters from
`parameter_key(seed)`, step k of epoch e from `step_key(seed, e, k)`. A run killed at any
point and resumed from a checkpoint therefore ends with the parameters of an uninterrupted
run, and a sweep member trains exactly as the single run of its seed.
"""

from __future__ import annotations

import functools
from typing import Any

import flax
import jax
import jax.numpy as jnp
import optax

from gst_jax.config import ModelConfig, TrainConfig
from gst_jax.model import Controls, Params, init_params
from gst_jax.training.schedules import make_schedule


@flax.struct.dataclass
class TrainState:
    """Everything that changes during training. A pytree, so it can be jitted, vmapped, saved."""

    params: Params
    opt_state: Any   # optax's state for `make_optimizer` (optax ships no types: Any for mypy)
    step: jax.Array  # () int32, optimiser steps taken


@flax.struct.dataclass
class HParams:
    """Per-step hyperparameters, traced so that changing them never recompiles.

    Attributes:
      controls: tau (the epoch's Gumbel temperature), n and the ghost switch of the rollout.
      learning_rate: () Adam's learning rate of the epoch.
      fully_detected_only: () bool, the paper's "F" baseline: partially detected pedestrians
        are removed from every training scene.
      score_partial: () bool, GST (P)'s loss scores the partially detected too
        (`TrainConfig.score_partial`).
      hide_history: () float32, the chance that a pedestrian's history is cut short
        (`TrainConfig.hide_history`).
    """

    controls: Controls
    learning_rate: jax.Array
    fully_detected_only: jax.Array
    score_partial: jax.Array
    hide_history: jax.Array


def make_optimizer() -> optax.GradientTransformation:
    """Adam with the learning rate injected as state, so `HParams.learning_rate` drives it."""
    return optax.inject_hyperparams(optax.adam)(learning_rate=1e-3)


@functools.partial(jax.jit, static_argnums=0)   # one program, not one per array (see init_params)
def create_train_state(model_config: ModelConfig, key: jax.Array) -> TrainState:
    params = init_params(model_config, key)
    return TrainState(params=params, opt_state=make_optimizer().init(params), step=jnp.int32(0))


def abstract_train_state(model_config: ModelConfig) -> TrainState:
    """Shapes and dtypes of a fresh state (a restore template), without initialising one."""
    return jax.eval_shape(lambda key: create_train_state(model_config, key), jax.random.key(0))


def hparams_for_epoch(model_config: ModelConfig, train_config: TrainConfig, epoch: int,
                      fully_detected_only: bool | None = None) -> HParams:
    """The HParams of a 1-based epoch under the run's schedule; n and ghost are the model
    config's."""
    if fully_detected_only is None:
        fully_detected_only = train_config.fully_detected_only
    learning_rate, tau = make_schedule(train_config).at(epoch)
    return HParams(controls=Controls.from_config(model_config, tau),
                   learning_rate=jnp.float32(learning_rate),
                   fully_detected_only=jnp.bool_(fully_detected_only),
                   score_partial=jnp.bool_(train_config.score_partial),
                   hide_history=jnp.float32(train_config.hide_history))


def parameter_key(seed: int) -> jax.Array:
    """The key of a run's initial parameters."""
    return jax.random.fold_in(jax.random.key(seed), 0)


def step_key(seed: int, epoch: int, step: int) -> jax.Array:
    """The key of optimiser step `step` (0-based) of a 1-based epoch."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), epoch), step)


def validation_key(seed: int, epoch: int) -> jax.Array:
    """The key of an epoch's validation samples: a stream of its own (fold_in takes uint32
    data, so the stream is the largest one rather than a negative epoch)."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), 2 ** 32 - 1), epoch)
