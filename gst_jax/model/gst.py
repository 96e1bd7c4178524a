"""The Gumbel Social Transformer as a Flax module with one method per stage.

`rollout.py` drives these methods over time; this module holds no loop over time.
"""

from __future__ import annotations

import functools
from typing import Any, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.graph import adjacency
from gst_jax.model.controls import Controls
from gst_jax.model.encoder import NodeEncoderLayer
from gst_jax.model.heads import READOUT_SIZE, head
from gst_jax.model.layers import DenseParams, torch_dense
from gst_jax.model.recurrent import MaskedLSTMCell
from gst_jax.model.selector import EdgeSelector, nearest_candidates, sample_edges
from gst_jax.model.temporal import TemporalConvReadout

Params = Mapping[str, Any]
"""A model's parameters: Flax's tree of named modules down to their arrays, as `init_params`
makes them and checkpoints, `gst_jax.runs.Run` and the shipped models hold them
(`params["tcn"]["time_conv_0"]["kernel"]`)."""


class GST(nn.Module):
    """Embeddings, edge selector, node encoder, and a temporal model: the masked LSTM with
    its output head (`recur`, `readout`), or the release's convolutional readout (`convolve`)."""

    config: ModelConfig

    def setup(self):
        config = self.config
        head(config.output)                      # an unknown output fails here, by name
        self.node_embedding = torch_dense(config.node_dim, 2)
        self.edge_embedding = DenseParams(config.edge_dim, 2)  # used in factorised form
        self.edge_selector = EdgeSelector(config)
        self.node_encoder_layers = [NodeEncoderLayer(config) for _ in range(config.encoder_layers)]
        if config.recurrent:
            self.lstm = MaskedLSTMCell(config.lstm_hidden)
            self.hidden2pos = torch_dense(READOUT_SIZE, config.lstm_hidden)
        else:
            self.tcn = TemporalConvReadout(config.obs_len, config.pred_len, READOUT_SIZE,
                                           dropout=config.dropout)

    def candidates(self, edge_features: jax.Array, node_mask: jax.Array) -> jax.Array | None:
        """Each target's candidate neighbours (..., N, K) at these steps, or None for the exact
        model (`ModelConfig.candidates`, docs/MODEL.md 2.4)."""
        count = self.config.candidates
        return nearest_candidates(edge_features, node_mask, count) if count else None

    def select(self, node_features: jax.Array, edge_features: jax.Array, node_mask: jax.Array,
               controls: Controls, *, deterministic: bool) -> jax.Array:
        """The edge selector's probabilities (..., N, G, N+1); inputs as for `interact`."""
        return self.edge_selector(self.node_embedding(node_features), edge_features,
                                  self.edge_embedding(), adjacency(node_mask), controls,
                                  deterministic=deterministic,
                                  candidates=self.candidates(edge_features, node_mask))

    def interact(self, node_features: jax.Array, edge_features: jax.Array, node_mask: jax.Array,
                 noise: jax.Array, controls: Controls, *, hard: bool, deterministic: bool,
                 edge_probs: jax.Array | None = None):
        """Sample the graph and encode every pedestrian's neighbourhood.

        node_features (..., N, 2), edge_features (..., N, N, 2) [j, i], node_mask (..., N),
        noise (..., N, G, N+1); edge_probs, if given, are `select`'s output for these inputs
        (shared between samples that differ only in their noise). Returns encoded nodes
        (..., N, d), edge_probs and sampled_edges (..., N, G, N+1), and attention weights
        (layers, ..., 8, N, N+1). With candidates (`ModelConfig.candidates`) the selector and
        the encoder's attention see each target's candidates and the ghost only.
        """
        edges = adjacency(node_mask)
        candidates = self.candidates(edge_features, node_mask)
        node_embedding = self.node_embedding(node_features)
        # Full connection (n = 0): the observed adjacency itself, no ghost; as edges, in the
        # first head slot.
        full = jnp.concatenate([edges, jnp.zeros_like(edges[..., :1])], axis=-1)
        first_head = jnp.arange(self.config.head_slots) == 0
        as_edges = jnp.where(first_head[:, None], full[..., None, :], 0.0)
        with_ghost_key: bool | jax.Array = False
        if self.config.selects_edges:
            if edge_probs is None:
                edge_probs = self.edge_selector(node_embedding, edge_features,
                                                self.edge_embedding(), edges, controls,
                                                deterministic=deterministic,
                                                candidates=candidates)
            sampled_edges, sampled_adjacency = sample_edges(edge_probs, noise, controls,
                                                            hard=hard)
            full_connection = controls.num_edge_heads == 0
            sampled_adjacency = jnp.where(full_connection, full, sampled_adjacency)
            sampled_adjacency = sampled_adjacency.at[..., -1].multiply(
                controls.ghost.astype(full.dtype))
            edge_probs = jnp.where(full_connection, as_edges, edge_probs)
            sampled_edges = jnp.where(full_connection, as_edges, sampled_edges)
            with_ghost_key = controls.ghost & ~full_connection
        else:                       # a program for full connection alone: no selector runs
            sampled_adjacency, edge_probs, sampled_edges = full, as_edges, as_edges

        x = node_embedding
        attention = []
        for layer in self.node_encoder_layers:
            x, weights = layer(x, node_mask, sampled_adjacency, with_ghost_key,
                               deterministic=deterministic, candidates=candidates)
            attention.append(weights)
        return x, edge_probs, sampled_edges, jnp.stack(attention)

    def recur(self, inputs: jax.Array, state: tuple[jax.Array, jax.Array],
              mask: jax.Array, *, hold: bool = True) -> tuple[jax.Array, jax.Array]:
        """One LSTM step on masked inputs: inputs (..., N, d), state (h, c) (..., N, H), mask
        (..., N). hold: where the mask is 0 the state is kept (else the step runs on the
        zeroed input, as gst_updated's faster_lstm observes)."""
        return self.lstm(inputs * mask[..., None], state,
                         mask if hold else jnp.ones_like(mask))

    def readout(self, hidden: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Gaussian parameters of the next displacement: mu (..., 2), sigma (..., 2), corr (...)."""
        return _gaussian(self.hidden2pos(hidden))

    def convolve(self, encoded: jax.Array, *, deterministic: bool):
        """TCN: Gaussian parameters of all P steps from encoded observations (B, T_obs, N, d)."""
        return _gaussian(self.tcn(encoded, deterministic=deterministic))

    def __call__(self, node_features, edge_features, node_mask, noise, controls):
        """Touch every parameter once (used by `init`); inputs have a time axis (1, T_obs, ...).
        The selector's are made even where the program runs none (one parameter layout)."""
        self.select(node_features, edge_features, node_mask, controls, deterministic=True)
        encoded, *_ = self.interact(node_features, edge_features, node_mask, noise, controls,
                                    hard=False, deterministic=True)
        if not self.config.recurrent:
            return self.convolve(encoded, deterministic=True)
        zeros = jnp.zeros(encoded.shape[:-1] + (self.config.lstm_hidden,))
        hidden, _ = self.recur(encoded, (zeros, zeros), node_mask)
        return self.readout(hidden)


def _gaussian(raw: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Raw head outputs (..., 5) -> mu (..., 2), sigma = exp (..., 2), corr = tanh (...)."""
    return raw[..., :2], jnp.exp(raw[..., 2:4]), jnp.tanh(raw[..., 4])


# One program: initialised op by op, the model took 9 s of every training's start on a CPU
# (2 s from the compilation cache); the parameters are the same to the bit.
@functools.partial(jax.jit, static_argnums=0)
def init_params(config: ModelConfig, key: jax.Array) -> Params:
    """Fresh parameters (PyTorch-style initialisation) for `config`."""
    n, steps = 4, (1, config.obs_len)
    node_mask = jnp.ones(steps + (n,))
    noise = jnp.zeros(steps + (n, config.head_slots, n + 1))
    controls = Controls.make(1.0, max(config.num_edge_heads, 1), True)
    variables = GST(config).init(key, jnp.zeros(steps + (n, 2)), jnp.zeros(steps + (n, n, 2)),
                                 node_mask, noise, controls)
    return variables["params"]
