"""Traced switches of one forward pass: temperature, number of edge heads, ghost agent."""

from __future__ import annotations

import flax
import jax
import jax.numpy as jnp

from gst_jax.config import EVAL_TAU, ModelConfig


@flax.struct.dataclass
class Controls:
    """Values that vary inside one compiled program (so changing them never recompiles).

    Attributes:
      tau: () float32 Gumbel-softmax temperature.
      num_edge_heads: () int32 n; 0 = full connection (no selector, no ghost).
      ghost: () bool, whether the ghost neighbour may be selected.
    """

    tau: jax.Array
    num_edge_heads: jax.Array
    ghost: jax.Array

    @classmethod
    def make(cls, tau: float, num_edge_heads: int, ghost: bool) -> "Controls":
        return cls(tau=jnp.float32(tau), num_edge_heads=jnp.int32(num_edge_heads),
                   ghost=jnp.bool_(ghost))

    @classmethod
    def from_config(cls, config: ModelConfig, tau: float = EVAL_TAU) -> "Controls":
        """The config's own n and ghost, at temperature `tau` (default: evaluation's 0.03)."""
        return cls.make(tau, config.num_edge_heads, config.ghost)
