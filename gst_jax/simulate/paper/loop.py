"""The closed loop: every detected agent moves by a model's first predicted displacement.

Holonomic agents on a plane, stepping on the scenario's time grid (the model's). Agent 0 is
the robot; it is an agent like the others. At every step each detected agent moves by the
first displacement a model predicts from the last obs_len observed steps of everyone
detected. An agent not yet detected walks its scripted straight line, unseen by the model,
until its detection step. The whole loop is one jitted `lax.scan` with the model call inside.

With `humans=ORCA_HUMANS` the people (every agent but the robot) walk instead as CrowdNav++'s
reactive humans do (`agents/orca.py`, its numbers): ORCA towards the far end of their scripted
line at its speed, seeing each other and the robot, detected or not; the model still moves
the robot from what it has detected.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from gst_jax.simulate.agents.motion import toward_goal
from gst_jax.simulate.agents.orca import OrcaParams, orca_velocities
from gst_jax.simulate.agents.predicted import StepModel
from gst_jax.simulate.paper.scenarios import Scenario

# How the people move: by the model, as the robot (the paper's), or by ORCA.
MODEL_HUMANS, ORCA_HUMANS = "model", "orca"
# ORCA humans, CrowdNav++'s: radius 0.3 m + 0.01 + its 0.15 m safety space for everyone (the
# robot too), a 5 s horizon, neighbours within 10 m; a goal this many seconds along the line.
ORCA_RADIUS, ORCA_HORIZON_S, ORCA_NEIGHBOUR_DIST, GOAL_AHEAD_S = 0.46, 5.0, 10.0, 100.0


def simulate(model: StepModel, scenario: Scenario, key: jax.Array, humans: str = MODEL_HUMANS
             ) -> jax.Array:
    """Positions (steps + 1, A, 2) of every agent, step 0 first. Jit-compiled closed loop."""
    run = jax.jit(functools.partial(episode, model, steps=scenario.steps, humans=humans,
                                    obs_len=scenario.grid.obs_len, step_s=scenario.grid.step_s))
    return run(jnp.asarray(scenario.start, jnp.float32),
               jnp.asarray(scenario.velocity, jnp.float32),
               jnp.asarray(scenario.detected_from), key)


def episode(model: StepModel, start: jax.Array, velocity: jax.Array, detected_from: jax.Array,
            key: jax.Array, *, steps: int, obs_len: int, step_s: float,
            humans: str = MODEL_HUMANS) -> jax.Array:
    """The closed loop of one episode, pure (vmap it over episodes): positions
    (steps + 1, A, 2) from start (A, 2), the scripted velocities (A, 2) m/s and the step from
    which each agent is detected (A,) (never, for an agent past `steps`: it walks its line
    unseen); the people moved as `humans` says (MODEL_HUMANS or ORCA_HUMANS)."""
    if humans not in (MODEL_HUMANS, ORCA_HUMANS):
        raise ValueError(f"humans must be {MODEL_HUMANS!r} or {ORCA_HUMANS!r}, got {humans!r}")
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
        if humans == ORCA_HUMANS:
            people = orca_people(history, start, velocity, step_s)
            move = move.at[1:].set(people[1:] * step_s)
        position = history[-1] + move
        return (jnp.concatenate([history[1:], position[None]]), key), position

    _, positions = jax.lax.scan(step, (history, key), jnp.arange(steps))
    return jnp.concatenate([start[None], positions])


def orca_people(history: jax.Array, start: jax.Array, velocity: jax.Array, step_s: float
                ) -> jax.Array:
    """Every agent's ORCA velocity (A, 2) from its last two positions in `history`
    (T, A, 2), each towards a goal far along its scripted line at that line's speed (still,
    for an agent without one). The robot's row is of no use (the model moves it); the
    others see it at its velocity."""
    position, now = history[-1], (history[-1] - history[-2]) / step_s
    speed = jnp.linalg.norm(velocity, axis=-1)
    preferred = toward_goal(position, start + velocity * GOAL_AHEAD_S, speed[:, None])
    count = position.shape[0]
    params = OrcaParams(ORCA_HORIZON_S, count - 1, ORCA_NEIGHBOUR_DIST)
    return orca_velocities(position, now, jnp.full(count, ORCA_RADIUS), speed, preferred,
                           jnp.ones(count, bool), params, step_s)
