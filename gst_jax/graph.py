"""Masked graph construction and masked attention, as pure jax.numpy functions.

Shapes: B scenes, T steps, N pedestrian slots. Edge tensors are indexed [..., j, i] with j
the neighbour and i the target, as in the release (`A[t, j, i] = x_j - x_i`).
"""

from __future__ import annotations

from typing import overload

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.data.batch import SceneBatch

__all__ = ["adjacency", "displacements", "drop_partially_detected", "edge_features",
           "float_mask_attention_weights", "masked_categorical", "masked_softmax_weights"]

# The release adds this to every normaliser so that fully masked rows give 0, not NaN.
EPS = 1e-10
# The smallest mask entry `masked_softmax_weights` takes the logarithm of.
TINY = 1e-30


def displacements(positions: jax.Array | np.ndarray, node_mask: jax.Array | np.ndarray
                  ) -> jax.Array:
    """Node features v^t = x^t - x^{t-1}, zero at t = 0 and where m^t = 0.

    positions (..., T, N, 2), node_mask (..., T, N) -> (..., T, N, 2).
    """
    steps = positions[..., 1:, :, :] - positions[..., :-1, :, :]
    v = jnp.concatenate([jnp.zeros_like(positions[..., :1, :, :]), steps], axis=-3)
    return v * node_mask[..., None]


@overload
def adjacency(node_mask: jax.Array) -> jax.Array: ...
@overload
def adjacency(node_mask: np.ndarray) -> np.ndarray: ...
def adjacency(node_mask):
    """a_ij = m_i m_j.  (..., N) -> (..., N, N)."""
    return node_mask[..., :, None] * node_mask[..., None, :]


def edge_features(positions: jax.Array | np.ndarray, node_mask: jax.Array | np.ndarray
                  ) -> jax.Array | np.ndarray:
    """A[..., j, i] = x_j - x_i where both nodes are valid, else 0.

    positions (..., N, 2), node_mask (..., N) -> (..., N, N, 2).
    """
    relative = positions[..., :, None, :] - positions[..., None, :, :]
    return relative * adjacency(node_mask)[..., None]


def float_mask_attention_weights(scores: jax.Array, mask: jax.Array) -> jax.Array:
    """The release's attention: softmax, multiply by a float mask, renormalise (+1e-10).

    Masked scores are not set to -inf first, so a fully masked row gives all zeros.
    scores (..., L, S), mask broadcastable to it -> (..., L, S).
    """
    weights = jax.nn.softmax(scores, axis=-1) * mask
    return weights / (jnp.sum(weights, axis=-1, keepdims=True) + EPS)


def masked_softmax_weights(scores: jax.Array, mask: jax.Array) -> jax.Array:
    """The softmax over the entries the mask keeps: masked scores count as -inf, so a row
    whose masked entries outscore its kept ones by any margin still sums to 1; a row with no
    kept entry gives all zeros. For a mask of 0s and 1s it equals the release's
    `float_mask_attention_weights` wherever that does not underflow. A fractional mask (a
    soft Gumbel sample) weights the kept entries as the release does, softmax(s) m / sum,
    computed as a softmax of s + log m, so that no row's normaliser can underflow however
    small its mask is.

    scores (..., L, S), mask broadcastable to it -> (..., L, S).
    """
    kept = jnp.broadcast_to(mask > 0, scores.shape)
    # Below TINY a mask entry counts as TINY: log m's gradient 1/m stays finite.
    logits = jnp.where(kept, scores + jnp.log(jnp.maximum(mask, TINY)), -jnp.inf)
    # The row's largest kept logit, 0 for a row with none (whose exponentials are all masked).
    top = jnp.max(logits, axis=-1, keepdims=True)
    top = jax.lax.stop_gradient(jnp.where(jnp.isfinite(top), top, 0.0))
    # The inner `where` keeps exp() (and its gradient) finite at masked entries; the largest
    # entry is exp(0) = 1, so a row's total is 0 or at least 1.
    weights = jnp.where(kept, jnp.exp(jnp.where(kept, logits - top, 0.0)), 0.0)
    total = jnp.sum(weights, axis=-1, keepdims=True)
    return weights / jnp.where(total > 0, total, 1.0)


# Each `ModelConfig.attention` kind: how attention and edge probabilities treat masked entries.
ATTENTION_WEIGHTS = {"release": float_mask_attention_weights, "masked": masked_softmax_weights}


def masked_categorical(logits: jax.Array, mask: jax.Array, kind: str = "release") -> jax.Array:
    """Edge probabilities p = softmax(logits) restricted to valid edges (docs/MODEL.md 2.1
    step 7), by the `ModelConfig.attention` kind's weights."""
    return ATTENTION_WEIGHTS[kind](logits, mask)


def drop_partially_detected(batch: SceneBatch, enabled: jax.Array | bool) -> SceneBatch:
    """Remove partially detected pedestrians from every scene when `enabled` (may be traced):
    the paper's "F" baseline, which observes only pedestrians tracked for the whole window."""
    keep = jnp.where(enabled, batch.fully_detected_mask, 1.0)[:, None, :]
    return batch._replace(positions=batch.positions * keep[..., None],
                               position_mask=batch.position_mask * keep,
                               node_mask=batch.node_mask * keep)
