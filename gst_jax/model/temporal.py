"""The release's temporal convolution readout (`st_model_tcn`, the paper's LSTM-vs-TCN study).

Instead of a recurrent rollout, the encoded observed steps go through residual convolutions
over time and are mapped to all predicted steps at once: no prediction-time interaction.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from gst_jax.model.layers import Dropout, layer_norm, torch_dense, torch_uniform


class TemporalConvReadout(nn.Module):
    """Residual time convolutions, then time and feature MLPs:
    (..., T_obs, N, d) -> (..., P, N, out).

    Each of `num_convs` blocks adds relu(conv_t(LayerNorm(x))) to x, a kernel-3 convolution
    along time only (pedestrians never mix). Time is then mapped T_obs -> P -> P and features
    d -> hidden -> out by linear layers with relu and dropout, as in the release.
    """

    obs_len: int
    pred_len: int
    features_out: int
    hidden: int = 32
    num_convs: int = 6
    kernel_size: int = 3
    dropout: float = 0.1

    @nn.compact
    def __call__(self, x: jax.Array, *, deterministic: bool) -> jax.Array:
        channels = x.shape[-1]
        fan_in = channels * self.kernel_size
        pad = (self.kernel_size - 1) // 2
        for i in range(self.num_convs):
            conv = nn.Conv(channels, (self.kernel_size, 1), padding=((pad, pad), (0, 0)),
                           kernel_init=torch_uniform(fan_in), bias_init=torch_uniform(fan_in),
                           name=f"time_conv_{i}")
            x = x + jax.nn.relu(conv(layer_norm(name=f"norm_{i}")(x)))
        dropout = Dropout(self.dropout)

        def drop(y):
            return dropout(y, deterministic=deterministic)

        x = jnp.moveaxis(x, -3, -1)                                  # (..., N, d, T_obs)
        x = drop(jax.nn.relu(torch_dense(self.pred_len, self.obs_len, "time_linear_1")(x)))
        x = drop(jax.nn.relu(torch_dense(self.pred_len, self.pred_len, "time_linear_2")(x)))
        x = jnp.moveaxis(x, -1, -3)                                  # (..., P, N, d)
        x = drop(jax.nn.relu(torch_dense(self.hidden, channels, "linear_1")(x)))
        return torch_dense(self.features_out, self.hidden, "linear_2")(x)
