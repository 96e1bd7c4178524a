"""Masked LSTM cell (docs/MODEL.md 2.3) in PyTorch's gate order, so release weights convert."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from gst_jax.model.layers import torch_uniform


class MaskedLSTMCell(nn.Module):
    """LSTM step with gates (i, f, g, o) whose state is kept where the mask is 0."""

    hidden: int

    @nn.compact
    def __call__(self, inputs: jax.Array, state: tuple[jax.Array, jax.Array],
                 mask: jax.Array) -> tuple[jax.Array, jax.Array]:
        """inputs: (..., D); state: (h, c) each (..., H); mask: (...,) -> new (h, c)."""
        init = torch_uniform(self.hidden)
        features = inputs.shape[-1]
        weight_ih = self.param("weight_ih", init, (features, 4 * self.hidden))
        weight_hh = self.param("weight_hh", init, (self.hidden, 4 * self.hidden))
        bias_ih = self.param("bias_ih", init, (4 * self.hidden,))
        bias_hh = self.param("bias_hh", init, (4 * self.hidden,))
        h, c = state
        gates = inputs @ weight_ih + bias_ih + h @ weight_hh + bias_hh
        i, f, g, o = jnp.split(gates, 4, axis=-1)
        new_c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(g)
        new_h = jax.nn.sigmoid(o) * jnp.tanh(new_c)
        keep = mask[..., None]
        return keep * new_h + (1 - keep) * h, keep * new_c + (1 - keep) * c
