"""Initialisers and small layers shared by the GST modules.

Parameters are initialised as PyTorch initialises the release's layers, so that training
from scratch starts where the release starts.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from gst_jax import noise


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


class Dropout(nn.Module):
    """Inverted dropout whose mask is a hash of each element's coordinates (`gst_jax.noise`).

    The mask of an element depends only on the 'dropout' key and its coordinates, not on
    the array's padded shape, so a window's masks do not change with its padding (the
    rollout runs the model on one window at a time, vmapped). With `ghost_axis`, the last
    index along that axis is the ghost neighbour and keeps its own masks whatever N is.
    Hashing also costs a few integer ops per element, where flax's threefry dropout of the
    selector's (T, N, N+1, 128) hidden layer took a quarter of a training step on CPU.
    """

    rate: float
    ghost_axis: int | None = None

    @nn.compact
    def __call__(self, x: jax.Array, *, deterministic: bool) -> jax.Array:
        if deterministic or self.rate == 0.0:
            return x
        keep = noise.dropout_mask(self.make_rng("dropout"), x.shape, self.rate,
                               ghost_axis=self.ghost_axis)
        return jnp.where(keep, x / (1.0 - self.rate), jnp.zeros_like(x))
