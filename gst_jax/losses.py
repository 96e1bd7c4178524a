"""Training losses of GST (D) and GST (P), per scene as in the release (docs/MODEL.md 3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gst_jax import graph
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.rollout import RolloutOutput


def _safe_ratio(numerator: jax.Array, denominator: jax.Array) -> jax.Array:
    """numerator / denominator, 0 where the denominator is 0 (padding scenes), NaN-free grads."""
    positive = denominator > 0
    return jnp.where(positive, numerator / jnp.where(positive, denominator, 1.0), 0.0)


def position_mse(displacements: jax.Array, true_displacements: jax.Array,
                 mask: jax.Array) -> jax.Array:
    """GST (D): masked squared error of cumulative positions, per scene.

    displacements, true_displacements: (B, P, N, 2); mask: (B, P, N) -> (B,).
    Masked steps add nothing to either cumulative sum, so a pedestrian who leaves adds no error.
    """
    predicted = jnp.cumsum(displacements * mask[..., None], axis=1)
    target = jnp.cumsum(true_displacements * mask[..., None], axis=1)
    squared = jnp.sum((predicted - target) ** 2, axis=-1)
    return _safe_ratio(jnp.sum(squared * mask, axis=(1, 2)), jnp.sum(mask, axis=(1, 2)))


def gaussian_nll(true_displacements: jax.Array, mu: jax.Array, sigma: jax.Array,
                 corr: jax.Array) -> jax.Array:
    """Bivariate Gaussian NLL per step without the log 2 pi term.  (..., 2) -> (...)."""
    normalised = (true_displacements - mu) / sigma
    nx, ny = normalised[..., 0], normalised[..., 1]
    one_minus_rho2 = 1.0 - corr ** 2
    return (jnp.log(sigma[..., 0]) + jnp.log(sigma[..., 1]) + 0.5 * jnp.log(one_minus_rho2)
            + (nx ** 2 - 2.0 * corr * nx * ny + ny ** 2) / (2.0 * one_minus_rho2))


def scene_losses(config: ModelConfig, output: RolloutOutput, batch: SceneBatch) -> jax.Array:
    """Per-scene training loss (B,) for the configured output type."""
    obs_len = config.obs_len
    true_displacements = graph.displacements(batch.positions, batch.node_mask)[:, obs_len:]
    if config.output == "gaussian":
        # Mean over the predicted steps, then over fully detected pedestrians only.
        nll = gaussian_nll(true_displacements, output.mu, output.sigma, output.corr)
        fully_detected = graph.fully_detected_mask(batch.node_mask)
        per_pedestrian = jnp.mean(jnp.where(fully_detected[:, None, :] > 0, nll, 0.0), axis=1)
        return _safe_ratio(jnp.sum(per_pedestrian * fully_detected, axis=-1),
                           jnp.sum(fully_detected, axis=-1))
    mask = batch.node_mask[:, obs_len:] * output.predicted_mask[:, None, :]
    return position_mse(output.displacements, true_displacements, mask)


def batch_loss(config: ModelConfig, output: RolloutOutput, batch: SceneBatch) -> jax.Array:
    """Mean of the per-scene losses over the real (non-padding) scenes of the batch."""
    return _safe_ratio(jnp.sum(scene_losses(config, output, batch) * batch.scene_mask),
                       jnp.sum(batch.scene_mask))
