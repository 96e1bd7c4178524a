"""Gumbel-softmax sampling of edges, as in the release (docs/MODEL.md 2.1 step 8).

Two twins: `sample_gumbel(key, shape)` draws the noise from an explicit key, and
`gumbel_softmax(log_probs, noise, tau, hard)` consumes it; replaying recorded noise through
the second is what makes exact parity tests possible.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gst_jax import noise
from gst_jax.graph import EPS


def sample_gumbel(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """g = -log(eps - log(u + eps)), u ~ U[0, 1): the release's (eps-guarded) Gumbel noise.

    shape (..., N + 1) with the ghost neighbour last; each element's draw depends on its
    coordinates only (`gst_jax.noise`), so a window's noise does not change with its padding.
    """
    uniform = noise.uniform(key, shape, ghost_axis=-1)
    return -jnp.log(EPS - jnp.log(uniform + EPS))


def gumbel_softmax(log_probs: jax.Array, noise: jax.Array, tau: jax.Array,
                   hard: bool) -> jax.Array:
    """Relaxed (or straight-through one-hot) samples over the last axis.

    log_probs: (..., K) log(p + 1e-10); noise: same shape; tau: temperature (traced).
    hard: one-hot of the argmax in the forward pass, gradients of the soft sample.
    """
    soft = jax.nn.softmax((log_probs + noise) / tau, axis=-1)
    if not hard:
        return soft
    one_hot = jax.nn.one_hot(jnp.argmax(soft, axis=-1), soft.shape[-1], dtype=soft.dtype)
    return one_hot - jax.lax.stop_gradient(soft) + soft
