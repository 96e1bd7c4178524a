"""Masked graph construction and masked attention, as pure jax.numpy functions.

Shapes: B scenes, T steps, N pedestrian slots. Edge tensors are indexed [..., j, i] with j
the neighbour and i the target, as in the release (`A[t, j, i] = x_j - x_i`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gst_jax.data.batch import SceneBatch

# The release adds this to every normaliser so that fully masked rows give 0, not NaN.
EPS = 1e-10


def displacements(positions: jax.Array, node_mask: jax.Array) -> jax.Array:
    """Node features v^t = x^t - x^{t-1}, zero at t = 0 and where m^t = 0.

    positions (..., T, N, 2), node_mask (..., T, N) -> (..., T, N, 2).
    """
    steps = positions[..., 1:, :, :] - positions[..., :-1, :, :]
    v = jnp.concatenate([jnp.zeros_like(positions[..., :1, :, :]), steps], axis=-3)
    return v * node_mask[..., None]


def adjacency(node_mask: jax.Array) -> jax.Array:
    """a_ij = m_i m_j.  (..., N) -> (..., N, N)."""
    return node_mask[..., :, None] * node_mask[..., None, :]


def edge_features(positions: jax.Array, node_mask: jax.Array) -> jax.Array:
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


def masked_categorical(logits: jax.Array, mask: jax.Array) -> jax.Array:
    """Edge probabilities p = softmax(logits) restricted to valid edges (docs/MODEL.md 2.1
    step 7)."""
    return float_mask_attention_weights(logits, mask)


def drop_partially_detected(batch: SceneBatch, enabled: jax.Array | bool) -> SceneBatch:
    """Remove partially detected pedestrians from every scene when `enabled` (may be traced):
    the paper's "F" baseline, which observes only pedestrians tracked for the whole window."""
    keep = jnp.where(enabled, batch.fully_detected_mask, 1.0)[:, None, :]
    return batch._replace(positions=batch.positions * keep[..., None],
                               position_mask=batch.position_mask * keep,
                               node_mask=batch.node_mask * keep)
