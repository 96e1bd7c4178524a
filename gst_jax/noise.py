"""Padding-invariant random draws: each element's draw is a hash of a key and its coordinates.

A window's Gumbel noise, Gaussian draws and dropout masks must not depend on how many
padding slots its batch has, nor on which other windows share its batch: that is what lets
a training step be computed in size-packed micro-batches and still equal the same windows
computed together (docs/MODEL.md 3). jax.random's threefry draws depend on the array shape,
so here the bits of element (x_0, ..., x_k) are a 32-bit hash of the key's two words and the
coordinates, mixed in one axis at a time. The neighbour axis of the edge selector has the
ghost last, at index N of a window padded to N slots; `ghost_axis` maps that last index to a
fixed coordinate so the ghost's draws do not move with the padding either.

The hash is MurmurHash3's 32-bit finaliser, a bijection whose output bits depend on every
input bit; two rounds per axis. Draws are uniform to 2^-24, which is what float32 resolves.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

# The coordinate that stands for the ghost neighbour (any value no window reaches).
GHOST = 0x7FFF_FFFF
_GOLDEN = 0x9E3779B9


def window_keys(key: jax.Array, window_index: ArrayLike) -> jax.Array:
    """(B,) keys, one per window: `key` folded with each window's index in its dataset split,
    so that a window's draws do not depend on which windows share its batch (padding scenes,
    index -1, get keys too; their outputs are masked)."""
    return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, window_index)


def _mix32(x: jax.Array) -> jax.Array:
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ (x >> 13)
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def element_bits(key: jax.Array, shape: Sequence[int], *, ghost_axis: int | None = None
                 ) -> jax.Array:
    """uint32 bits of `shape`; element x's bits depend only on the key and x's coordinates
    (with the last index of `ghost_axis` read as GHOST)."""
    seed = jax.random.bits(key, (2,), jnp.uint32)
    rank = len(shape)
    ghost_axis = None if ghost_axis is None else ghost_axis % rank
    bits = _mix32(seed[0] ^ jnp.uint32(_GOLDEN))
    for axis, size in enumerate(shape):
        index = jnp.arange(size, dtype=jnp.uint32)
        if axis == ghost_axis:
            index = index.at[-1].set(GHOST)
        # Grow the hash one axis at a time: only the last axes are hashed at full size.
        bits = _mix32(_mix32(bits[..., None] ^ (index * jnp.uint32(_GOLDEN) + seed[1])))
    return bits.reshape(tuple(shape))


def uniform(key: jax.Array, shape: Sequence[int], *, ghost_axis: int | None = None) -> jax.Array:
    """float32 uniform on [0, 1) in steps of 2^-24."""
    bits = element_bits(key, shape, ghost_axis=ghost_axis)
    return (bits >> 8).astype(jnp.float32) * jnp.float32(2.0 ** -24)


def normal(key: jax.Array, shape: Sequence[int]) -> jax.Array:
    """float32 standard normals (inverse CDF of a uniform strictly inside (0, 1))."""
    return standard_normal_quantile(uniform(key, shape))


def standard_normal_quantile(u: jax.Array) -> jax.Array:
    """The normal draw of a `uniform` value u in [0, 1) (steps of 2^-24): the quantile at the
    middle of u's cell. The top cell's middle, 1 - 2^-25, rounds to 1 in float32, where the
    quantile is infinite, so it is taken at 1 - 2^-24 instead (about 5.3)."""
    u = jnp.minimum(u + jnp.float32(2.0 ** -25), jnp.float32(1.0 - 2.0 ** -24))
    return jnp.sqrt(jnp.float32(2.0)) * jax.lax.erf_inv(2.0 * u - 1.0)


def dropout_mask(key: jax.Array, shape: Sequence[int], rate: float, *,
              ghost_axis: int | None = None) -> jax.Array:
    """bool Bernoulli(1 - rate) of `shape` (dropout's keep mask), exact to 2^-32."""
    bits = element_bits(key, shape, ghost_axis=ghost_axis)
    return bits >= jnp.uint32(int(rate * 2 ** 32))
