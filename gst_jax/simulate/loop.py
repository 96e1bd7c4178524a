"""The closed loop: every detected agent moves by a model's first predicted displacement.

Holonomic agents on a plane, stepping on the scenario's time grid (the model's). Agent 0 is
the robot; it is an agent like the others. At every step each detected agent moves by the
first displacement a model predicts from the last obs_len observed steps of everyone
detected. An agent not yet detected walks its scripted straight line, unseen by the model,
until its detection step. The whole loop is one jitted `lax.scan` with the model call inside.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch, node_mask_from_positions
from gst_jax.model import Controls
from gst_jax.rollout import rollout
from gst_jax.simulate.scenarios import Scenario

# A model: (positions (T_obs, A, 2), mask (T_obs, A), key) -> next displacement (A, 2).
StepModel = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


def constant_velocity_model(positions: jax.Array, mask: jax.Array, key: jax.Array) -> jax.Array:
    """Repeat each agent's last observed displacement (zero without two observations)."""
    both = mask[-1] * mask[-2]
    return (positions[-1] - positions[-2]) * both[:, None]


def gst_model(params, config: ModelConfig, controls: Controls) -> StepModel:
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


def simulate(model: StepModel, scenario: Scenario, key: jax.Array) -> jax.Array:
    """Positions (steps + 1, A, 2) of every agent, step 0 first. Jit-compiled closed loop."""
    run = jax.jit(functools.partial(episode, model, steps=scenario.steps,
                                    obs_len=scenario.grid.obs_len, step_s=scenario.grid.step_s))
    return run(jnp.asarray(scenario.start, jnp.float32),
               jnp.asarray(scenario.velocity, jnp.float32),
               jnp.asarray(scenario.detected_from), key)


def episode(model: StepModel, start: jax.Array, velocity: jax.Array, detected_from: jax.Array,
            key: jax.Array, *, steps: int, obs_len: int, step_s: float) -> jax.Array:
    """The closed loop of one episode, pure (vmap it over episodes): positions
    (steps + 1, A, 2) from start (A, 2), the scripted velocities (A, 2) m/s and the step from
    which each agent is detected (A,) (never, for an agent past `steps`: it walks its line
    unseen)."""
    # Agents seen from step 0 are also seen during their history before it.
    first_seen = jnp.where(detected_from == 0, -obs_len, detected_from)
    history = start[None] + velocity[None] * step_s * jnp.arange(-obs_len + 1, 1)[:, None, None]

    def step(carry, t):
        history, key = carry
        key, model_key = jax.random.split(key)
        # Steps t - obs_len + 1 .. t: seen where the agent was already detected then.
        seen = ((t - obs_len + 1 + jnp.arange(obs_len))[:, None] >= first_seen[None])
        predicted = model(history, seen.astype(jnp.float32), model_key)
        detected_now = (t >= detected_from)[:, None]
        move = jnp.where(detected_now, predicted, velocity * step_s)
        position = history[-1] + move
        return (jnp.concatenate([history[1:], position[None]]), key), position

    _, positions = jax.lax.scan(step, (history, key), jnp.arange(steps))
    return jnp.concatenate([start[None], positions])
