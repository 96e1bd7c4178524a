"""Output heads: what a predicted step is drawn from, and what training minimises.

The temporal model's readout gives five numbers per pedestrian and step, a bivariate Gaussian
(mu (2,), sigma = exp (2,), corr = tanh); a head says how the step's displacement is drawn
from them and how a scene's training loss is computed (docs/MODEL.md 2.2, 3). `HEADS` holds
every head by the name `--output` gives it: adding a head is adding one entry here.

    deterministic   GST (D): the displacement is mu; loss: squared error of positions
    gaussian        GST (P): the displacement is sampled; loss: Gaussian NLL
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

__all__ = ["HEADS", "Head", "Losses", "gaussian_nll", "head", "position_mse", "safe_ratio",
           "sample_displacement"]

# The readout's width: mu (2), log sigma (2), the correlation's pre-tanh (1).
READOUT_SIZE = 5


@dataclasses.dataclass(frozen=True)
class Losses:
    """What a head's loss sees of one batch. P predicted steps, N pedestrian slots.

    displacements: (B, P, N, 2) the drawn displacements; mu, sigma (B, P, N, 2), corr
    (B, P, N): the readout; true_displacements (B, P, N, 2); step_mask (B, P, N) 1 where a
    predicted pedestrian's true displacement exists; fully_detected (B, N); score_partial:
    () bool, may be traced: GST (P)'s loss scores every predicted pedestrian at its steps of
    step_mask, not only the fully detected (`TrainConfig.score_partial`).
    """

    displacements: jax.Array
    mu: jax.Array
    sigma: jax.Array
    corr: jax.Array
    true_displacements: jax.Array
    step_mask: jax.Array
    fully_detected: jax.Array
    score_partial: jax.Array | bool = False


@dataclasses.dataclass(frozen=True)
class Head:
    """One output head.

    letter: its mark in run names (`eth-paper-<letter>-n1-...`).
    sampled: whether its draws are random (K samples differ; a drawn displacement is fed back
      detached, as the release's `detach_sample`).
    draw: (mu, sigma, corr, normal) -> displacement; normal (..., 2) standard normals.
    scene_loss: Losses -> (B,) per-scene training loss.
    """

    letter: str
    sampled: bool
    draw: Callable[[jax.Array, jax.Array, jax.Array, jax.Array], jax.Array]
    scene_loss: Callable[[Losses], jax.Array]


def safe_ratio(numerator: jax.Array, denominator: jax.Array) -> jax.Array:
    """numerator / denominator, 0 where the denominator is 0 (padding scenes), NaN-free grads."""
    positive = denominator > 0
    return jnp.where(positive, numerator / jnp.where(positive, denominator, 1.0), 0.0)


def position_mse(displacements: jax.Array, true_displacements: jax.Array,
                 mask: jax.Array) -> jax.Array:
    """Masked squared error of cumulative positions, per scene.

    displacements, true_displacements: (B, P, N, 2); mask: (B, P, N) -> (B,).
    Masked steps add nothing to either cumulative sum, so a pedestrian who leaves adds no error.
    """
    predicted = jnp.cumsum(displacements * mask[..., None], axis=1)
    target = jnp.cumsum(true_displacements * mask[..., None], axis=1)
    squared = jnp.sum((predicted - target) ** 2, axis=-1)
    return safe_ratio(jnp.sum(squared * mask, axis=(1, 2)), jnp.sum(mask, axis=(1, 2)))


def gaussian_nll(true_displacements: jax.Array, mu: jax.Array, sigma: jax.Array,
                 corr: jax.Array) -> jax.Array:
    """Bivariate Gaussian NLL per step without the log 2 pi term.  (..., 2) -> (...)."""
    normalised = (true_displacements - mu) / sigma
    nx, ny = normalised[..., 0], normalised[..., 1]
    one_minus_rho2 = 1.0 - corr ** 2
    return (jnp.log(sigma[..., 0]) + jnp.log(sigma[..., 1]) + 0.5 * jnp.log(one_minus_rho2)
            + (nx ** 2 - 2.0 * corr * nx * ny + ny ** 2) / (2.0 * one_minus_rho2))


def sample_displacement(mu: jax.Array, sigma: jax.Array, corr: jax.Array,
                        normal: jax.Array) -> jax.Array:
    """Reparameterised bivariate Gaussian draw: mu + (sx e1, rho sy e1 + sqrt(1-rho^2) sy e2)."""
    e1, e2 = normal[..., 0], normal[..., 1]
    dx = sigma[..., 0] * e1
    dy = sigma[..., 1] * (corr * e1 + jnp.sqrt(1.0 - corr ** 2) * e2)
    return mu + jnp.stack([dx, dy], axis=-1)


def _mean_displacement(mu, sigma, corr, normal):
    return mu


def _position_mse_loss(losses: Losses) -> jax.Array:
    return position_mse(losses.displacements, losses.true_displacements, losses.step_mask)


def _gaussian_nll_loss(losses: Losses) -> jax.Array:
    """The release's: mean NLL over the predicted steps, then over fully detected
    pedestrians only; with `score_partial`, each predicted pedestrian's mean NLL over the
    steps its future exists, then over those pedestrians."""
    nll = gaussian_nll(losses.true_displacements, losses.mu, losses.sigma, losses.corr)
    fully_detected = losses.fully_detected
    per_pedestrian = jnp.mean(jnp.where(fully_detected[:, None, :] > 0, nll, 0.0), axis=1)
    release = safe_ratio(jnp.sum(per_pedestrian * fully_detected, axis=-1),
                         jnp.sum(fully_detected, axis=-1))
    if losses.score_partial is False:
        return release
    steps = jnp.sum(losses.step_mask, axis=1)                                    # (B, N)
    per_pedestrian = safe_ratio(jnp.sum(jnp.where(losses.step_mask > 0, nll, 0.0), axis=1),
                                steps)
    scored = (steps > 0).astype(nll.dtype)
    partial = safe_ratio(jnp.sum(per_pedestrian * scored, axis=-1), jnp.sum(scored, axis=-1))
    return jnp.where(losses.score_partial, partial, release)


HEADS: dict[str, Head] = {
    "deterministic": Head(letter="d", sampled=False, draw=_mean_displacement,
                          scene_loss=_position_mse_loss),
    "gaussian": Head(letter="p", sampled=True, draw=sample_displacement,
                     scene_loss=_gaussian_nll_loss),
}


def head(name: str) -> Head:
    """The head of `ModelConfig.output`; a ValueError names the known ones."""
    try:
        return HEADS[name]
    except KeyError:
        raise ValueError(f"output {name!r}: expected one of {', '.join(HEADS)}") from None
