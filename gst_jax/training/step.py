"""The training loss and the jittable training step (docs/MODEL.md 3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from gst_jax import augment, losses
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.graph import drop_partially_detected
from gst_jax.rollout import rollout
from gst_jax.training.state import HParams, TrainState, make_optimizer


def training_loss(params, key: jax.Array, batch: SceneBatch, config: ModelConfig,
                  hparams: HParams, *, rotate: bool) -> jax.Array:
    """Mean over real scenes of the per-scene training loss (soft Gumbel samples, dropout on)."""
    rotate_key, rollout_key = jax.random.split(key)
    if rotate:
        batch = augment.rotate(rotate_key, batch)
    batch = drop_partially_detected(batch, hparams.fully_detected_only)
    output = rollout(params, rollout_key, batch, config, hparams.controls, hard=False,
                     deterministic=False)
    return losses.batch_loss(config, output, batch)


def make_train_step(config: ModelConfig, *, rotate: bool = True):
    """Build `train_step(state, key, batch, hparams) -> (state, metrics)`, not yet jitted.

    A step whose loss or gradients are not finite leaves the state unchanged and reports
    `finite = False`; the epoch loop decides what that means (stop, or count and go on).
    """
    optimizer = make_optimizer()

    def train_step(state: TrainState, key: jax.Array, batch: SceneBatch, hparams: HParams):
        loss, grads = jax.value_and_grad(training_loss)(state.params, key, batch, config,
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
