"""Training-time augmentation: a random rotation of every scene (docs/MODEL.md 3) and, an
option of gst_jax's (`TrainConfig.hide_history`), histories cut short at random."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gst_jax import noise
from gst_jax.data import SceneBatch, node_mask_from_positions


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


def hide_history(key: jax.Array, batch: SceneBatch, probability: jax.Array | float,
                 obs_len: int) -> SceneBatch:
    """Each pedestrian of each window, with `probability` (may be traced), seen only from
    observed step k on, k uniform in 1..obs_len - 2: a person who has just come into a
    sensor's range, as a robot sees many. The last two observed steps stay, so the
    pedestrians predicted are the same; with probability 0 the batch is unchanged. Each
    window's draws come from its own key (`noise.window_keys`)."""
    if obs_len < 3:                   # nothing can be hidden before the last two steps
        return batch
    steps, people = batch.positions.shape[1], batch.positions.shape[2]

    def draws(key):
        hide_key, start_key = jax.random.split(key)
        hidden = jax.random.uniform(hide_key, (people,)) < probability
        start = jax.random.randint(start_key, (people,), 1, max(obs_len - 1, 2))
        return jnp.where(hidden, start, 0)                                          # (N,)

    start = jax.vmap(draws)(noise.window_keys(key, batch.window_index))            # (B, N)
    seen = (jnp.arange(steps)[None, :, None] >= start[:, None, :]).astype(
        batch.position_mask.dtype)                                                  # (B, T, N)
    position_mask = batch.position_mask * seen
    return batch._replace(positions=batch.positions * seen[..., None],
                          position_mask=position_mask,
                          node_mask=batch.node_mask * node_mask_from_positions(position_mask))
