"""Training-time augmentation: a random rotation of every scene (docs/MODEL.md 3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gst_jax import noise
from gst_jax.data import SceneBatch


def rotate(key: jax.Array, batch: SceneBatch) -> SceneBatch:
    """Rotate each scene about the origin by an angle uniform in [0, 2 pi).

    The model sees only displacements and relative positions, so the centre of rotation does
    not matter; missing positions stay zero. Each window's angle comes from its own key
    (`noise.window_keys`), whatever else is in the batch.
    """
    angle = jax.vmap(lambda k: jax.random.uniform(k, maxval=2 * jnp.pi))(
        noise.window_keys(key, batch.window_index))
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    rotation = jnp.stack([jnp.stack([cos, -sin], -1), jnp.stack([sin, cos], -1)], -2)  # (B, 2, 2)
    positions = jnp.einsum("bxy,btny->btnx", rotation, batch.positions)
    return batch._replace(positions=positions)
