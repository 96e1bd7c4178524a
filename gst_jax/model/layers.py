"""Initialisers and small layers shared by the GST modules.

Parameters are initialised as PyTorch initialises the release's layers, so that training
from scratch starts where the release starts.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp


def torch_uniform(fan_in: int):
    """U(-1/sqrt(fan_in), 1/sqrt(fan_in)): PyTorch's default for Linear and LSTM parameters."""
    bound = 1.0 / math.sqrt(fan_in)

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def torch_dense(features: int, fan_in: int, name: str | None = None) -> nn.Dense:
    """A Dense layer initialised like torch.nn.Linear(fan_in, features)."""
    return nn.Dense(features, kernel_init=torch_uniform(fan_in), bias_init=torch_uniform(fan_in),
                    name=name)


def layer_norm(name: str | None = None) -> nn.LayerNorm:
    """torch.nn.LayerNorm's epsilon (1e-5), not flax's default (1e-6)."""
    return nn.LayerNorm(epsilon=1e-5, name=name)


class DenseParams(nn.Module):
    """The (kernel, bias) of a torch-initialised Linear(fan_in, features), for layers whose
    product is computed in factorised form rather than by calling the layer."""

    features: int
    fan_in: int

    @nn.compact
    def __call__(self) -> tuple[jax.Array, jax.Array]:
        init = torch_uniform(self.fan_in)
        return (self.param("kernel", init, (self.fan_in, self.features)),
                self.param("bias", init, (self.features,)))


class LayerNormParams(nn.Module):
    """The (scale, bias) of a LayerNorm over `features`, for factorised use."""

    features: int

    @nn.compact
    def __call__(self) -> tuple[jax.Array, jax.Array]:
        return (self.param("scale", nn.initializers.ones, (self.features,)),
                self.param("bias", nn.initializers.zeros, (self.features,)))


def _mix32(x: jax.Array) -> jax.Array:
    """MurmurHash3's 32-bit finaliser: a bijection whose output bits all depend on every input bit."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ (x >> 13)
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


class Dropout(nn.Module):
    """Inverted dropout whose mask is a counter-based hash of the element index.

    flax's nn.Dropout draws threefry bits for every element; for the edge selector's hidden
    layer, B x T x N x (N+1) x 128 elements per call, that took about a quarter of a training
    step on CPU. Here two 32-bit words drawn from the 'dropout' key seed two rounds of
    MurmurHash3's finaliser over the flat element index: Bernoulli(1 - rate) up to 2^-32,
    with independent-looking masks per call, at the cost of a few integer ops per element.
    """

    rate: float

    @nn.compact
    def __call__(self, x: jax.Array, *, deterministic: bool) -> jax.Array:
        if deterministic or self.rate == 0.0:
            return x
        seed = jax.random.bits(self.make_rng("dropout"), (2,), jnp.uint32)
        index = jnp.arange(x.size, dtype=jnp.uint32).reshape(x.shape)
        bits = _mix32(_mix32(index * jnp.uint32(0x9E3779B9) + seed[0]) ^ seed[1])
        keep = bits >= jnp.uint32(int(self.rate * 2 ** 32))
        return jnp.where(keep, x / (1.0 - self.rate), jnp.zeros_like(x))
