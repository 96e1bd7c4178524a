"""Node Transformer Encoder layer (docs/MODEL.md 2.2): attention over the sampled neighbours.

With a candidate neighbourhood (docs/MODEL.md 2.4) each target's keys and values are gathered
from its K candidates and the ghost, (N, K+1) scores instead of (N, N+1). The sampled graph
is zero outside the candidates, so this changes only which keys the softmax normalises over
before the graph masks it (its renormalisation's 1e-10 aside, the same weights).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.graph import ATTENTION_WEIGHTS
from gst_jax.model.layers import Dropout, layer_norm, torch_dense, torch_uniform
from gst_jax.model.selector import gather_neighbours, scatter_neighbours, with_ghost


class NodeEncoderLayer(nn.Module):
    """Pre-norm transformer layer whose attention weights are masked by the sampled graph."""

    config: ModelConfig

    def setup(self):
        d = self.config.node_dim
        self.norm_node = layer_norm()
        self.norm1_node = layer_norm()
        # torch.nn.MultiheadAttention: a xavier-uniform in_proj with zero bias; its out_proj is
        # a plain Linear (U(+-1/sqrt(d))) whose bias is then zeroed.
        self.in_proj = nn.Dense(3 * d, kernel_init=nn.initializers.xavier_uniform())
        self.out_proj = nn.Dense(d, kernel_init=torch_uniform(d))
        self.linear1 = torch_dense(self.config.encoder_ff_dim, d)
        self.linear2 = torch_dense(d, self.config.encoder_ff_dim)
        self.dropout = Dropout(self.config.dropout)
        # The release's attention drops its weights too (torch's MHA dropout), ghost last.
        self.attention_dropout = Dropout(self.config.dropout, ghost_axis=-1)

    def __call__(self, x: jax.Array, node_valid: jax.Array, sampled_adjacency: jax.Array,
                 with_ghost_key: jax.Array | bool, *, deterministic: bool,
                 candidates: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
        """x: (..., N, d); node_valid: (..., N); sampled_adjacency: (..., N, N+1) (ghost last);
        with_ghost_key: () whether the ghost's key takes part in the softmax (the release's
        ghost models); without, the model has no ghost key at all (its no-ghost models and full
        connection), which matters where the ghost's score would outweigh every other.
        candidates: (..., N, K) the only neighbours each target may attend to, None = all.

        Returns the new x (..., N, d) and the attention weights (..., heads, N, N+1).
        """
        heads = self.config.encoder_heads
        d = self.config.node_dim
        x = self.norm_node(x) * node_valid[..., None]
        num_nodes = x.shape[-2]
        # Keys and values include a zero ghost row, unless a program never has a ghost key
        # (with_ghost_key statically False: full connection alone).
        no_ghost = with_ghost_key is False
        keys = x if no_ghost else jnp.concatenate([x, jnp.zeros_like(x[..., :1, :])], axis=-2)
        qkv = self.in_proj(keys)
        q, k, v = qkv[..., :num_nodes, :d], qkv[..., d:2 * d], qkv[..., 2 * d:]
        mask, per = sampled_adjacency, ""
        if candidates is not None:
            # Each target's keys and values are its candidates' rows (and the ghost's): a
            # target axis on them, which `per` adds to the exact model's subscripts.
            neighbours = with_ghost(candidates, num_nodes)                   # (..., N, K+1)
            rows = candidates if no_ghost else neighbours
            k, v = gather_neighbours(k, rows), gather_neighbours(v, rows)    # (..., N, K+1, d)
            mask = jnp.take_along_axis(sampled_adjacency, neighbours, axis=-1, mode="clip")
            per = "l"
        split = lambda t: t.reshape(t.shape[:-1] + (heads, d // heads))
        scores = jnp.einsum(f"...lhc,...{per}mhc->...hlm", split(q), split(k)) / jnp.sqrt(
            d // heads)
        keys_without_ghost = scores.shape[-1] - (0 if no_ghost else 1)
        ghost_score = (jnp.full_like(scores[..., -1], -jnp.inf) if no_ghost else
                       jnp.where(with_ghost_key, scores[..., -1], -jnp.inf))
        scores = jnp.concatenate([scores[..., :keys_without_ghost], ghost_score[..., None]],
                                 axis=-1)
        weights = ATTENTION_WEIGHTS[self.config.attention](scores, mask[..., None, :, :])
        kept = self.attention_dropout(weights, deterministic=deterministic)
        attended = jnp.einsum(f"...hlm,...{per}mhc->...lhc", kept[..., :v.shape[-2]],
                              split(v)).reshape(x.shape)
        if candidates is not None:
            weights = scatter_neighbours(weights, candidates[..., None, :, :], num_nodes)
        # The residual adds to the normalised x, as the release does.
        x = x + self.dropout(self.out_proj(attended), deterministic=deterministic)
        feed_forward = self.linear2(self.dropout(nn.relu(self.linear1(self.norm1_node(x))),
                                                 deterministic=deterministic))
        return x + self.dropout(feed_forward, deterministic=deterministic), weights
