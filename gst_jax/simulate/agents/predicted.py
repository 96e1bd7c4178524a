"""Agents moved by a trajectory predictor: each detected agent takes the first displacement a
model predicts from everyone's last obs_len observed steps (the paper's closed loop, Fig. 5).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch, node_mask_from_positions
from gst_jax.model import Controls, Params
from gst_jax.rollout import rollout

# A model: (positions (T_obs, A, 2), mask (T_obs, A), key) -> next displacement (A, 2).
StepModel = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


def constant_velocity_model(positions: jax.Array, mask: jax.Array, key: jax.Array) -> jax.Array:
    """Repeat each agent's last observed displacement (zero without two observations)."""
    both = mask[-1] * mask[-2]
    return (positions[-1] - positions[-2]) * both[:, None]


def gst_model(params: Params, config: ModelConfig, controls: Controls) -> StepModel:
    """The first predicted displacement of a GST (hard samples, no dropout)."""
    if config.recurrent:
        # The first displacement comes from the observed state, before any predicted step;
        # the TCN readout's layers are sized by pred_len, so it keeps them.
        config = dataclasses.replace(config, pred_len=1)

    def step(positions, mask, key):
        pad = config.pred_len
        positions = jnp.concatenate([positions, jnp.zeros((pad,) + positions.shape[1:])])
        mask = jnp.concatenate([mask, jnp.zeros((pad,) + mask.shape[1:])])
        batch = SceneBatch(positions=positions[None] * mask[None, ..., None],
                           position_mask=mask[None], node_mask=node_mask_from_positions(mask)[None],
                           scene_mask=jnp.ones(1), window_index=jnp.zeros(1, jnp.int32))
        out = rollout(params, key, batch, config, controls, hard=True, deterministic=True)
        return out.displacements[0, 0]

    return step
