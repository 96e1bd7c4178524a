"""The closed loop: every detected agent moves by a model's first predicted displacement.

Holonomic agents on a plane, 0.4 s steps. Agent 0 is the robot; it is an agent like the
others. At every step each detected agent moves by the first displacement a model predicts
from the last 8 observed steps of everyone detected. An agent not yet detected walks its
scripted straight line, unseen by the model, until its detection step. The whole loop is one
jitted `lax.scan` with the model call inside.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.model import Controls
from gst_jax.rollout import rollout
from gst_jax.simulate.scenarios import DT, OBS_LEN, Scenario

# A model: (positions (T_obs, A, 2), mask (T_obs, A), key) -> next displacement (A, 2).
StepModel = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


def constant_velocity_model(positions: jax.Array, mask: jax.Array, key: jax.Array) -> jax.Array:
    """Repeat each agent's last observed displacement (zero without two observations)."""
    both = mask[-1] * mask[-2]
    return (positions[-1] - positions[-2]) * both[:, None]


def gst_model(params, config: ModelConfig, controls: Controls) -> StepModel:
    """The first predicted displacement of a GST (hard samples, no dropout)."""
    if config.temporal == "lstm":
        # The first displacement comes from the observed state, before any predicted step;
        # the TCN readout's layers are sized by pred_len, so it keeps them.
        config = dataclasses.replace(config, pred_len=1)

    def step(positions, mask, key):
        pad = config.pred_len
        positions = jnp.concatenate([positions, jnp.zeros((pad,) + positions.shape[1:])])
        mask = jnp.concatenate([mask, jnp.zeros((pad,) + mask.shape[1:])])
        node_mask = jnp.concatenate([mask[:1], mask[1:] * mask[:-1]])   # docs/MODEL.md 1.6
        batch = SceneBatch(positions=positions[None] * mask[None, ..., None],
                           position_mask=mask[None], node_mask=node_mask[None],
                           scene_mask=jnp.ones(1), window_index=jnp.zeros(1, jnp.int32))
        out = rollout(params, key, batch, config, controls, hard=True, deterministic=True)
        return out.displacements[0, 0]

    return step


def simulate(model: StepModel, scenario: Scenario, key: jax.Array) -> jax.Array:
    """Positions (steps + 1, A, 2) of every agent, step 0 first. Jit-compiled closed loop."""
    start = jnp.asarray(scenario.start, jnp.float32)
    velocity = jnp.asarray(scenario.velocity, jnp.float32)
    # Agents seen from step 0 are also seen during their 8-step history before it.
    detected_from = jnp.asarray(scenario.detected_from)
    first_seen = jnp.where(detected_from == 0, -OBS_LEN, detected_from)
    history = start[None] + velocity[None] * DT * jnp.arange(-OBS_LEN + 1, 1)[:, None, None]

    @jax.jit
    def run(key):
        def step(carry, t):
            history, key = carry
            key, model_key = jax.random.split(key)
            # Steps t-7..t: seen where the agent was already detected at that step.
            seen = ((t - OBS_LEN + 1 + jnp.arange(OBS_LEN))[:, None] >= first_seen[None])
            seen = seen.astype(jnp.float32)
            predicted = model(history, seen, model_key)
            detected_now = (t >= detected_from)[:, None]
            move = jnp.where(detected_now, predicted, velocity * DT)
            position = history[-1] + move
            return (jnp.concatenate([history[1:], position[None]]), key), position

        _, positions = jax.lax.scan(step, (history, key), jnp.arange(scenario.steps))
        return jnp.concatenate([start[None], positions])

    return run(key)
