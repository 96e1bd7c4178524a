"""How agents move one step, for both simulators: a holonomic body under a velocity command,
the velocity towards a goal that ORCA's agents prefer, and CrowdNav++'s social force.

Pure functions of arrays (A agents: positions and velocities (A, 2) in m and m/s, radii and
speeds (A,)), so that the paper's closed loop (`paper/loop.py`) and CrowdNav++'s task
(`crowdnav/environment.py`) move their people by the same rules.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class SocialForce(NamedTuple):
    """A social force's strength A, range B (m) and inverse relocation time KI (1/s); CrowdNav++'s
    values are `crowdnav.environment.EnvParams`' defaults."""

    strength: float | jax.Array
    range: float | jax.Array
    relocation_rate: float | jax.Array


def holonomic(position: jax.Array, velocity: jax.Array, max_speed, step_s: float
              ) -> tuple[jax.Array, jax.Array]:
    """A holonomic body's (position, velocity) after one step under the command `velocity`
    (..., 2), scaled down to `max_speed` where faster."""
    speed = jnp.linalg.norm(velocity, axis=-1, keepdims=True)
    velocity = jnp.where(speed > max_speed,
                         velocity * max_speed / jnp.maximum(speed, 1e-9), velocity)
    return position + velocity * step_s, velocity


def toward_goal(position: jax.Array, goal: jax.Array, factor=1.0) -> jax.Array:
    """The velocity an ORCA agent prefers (A, 2), CrowdNav++'s: towards its goal at 1 m/s,
    the offset itself within 1 m of it (times `factor`; ORCA caps it at the agent's speed)."""
    to_goal = goal - position
    distance = jnp.linalg.norm(to_goal, axis=-1, keepdims=True)
    return factor * jnp.where(distance > 1.0, to_goal / jnp.maximum(distance, 1e-9), to_goal)


def social_force_velocities(position: jax.Array, velocity: jax.Array, goal: jax.Array,
                            radius: jax.Array, v_pref: jax.Array, others: jax.Array,
                            others_radius: jax.Array, force: SocialForce, step_s: float
                            ) -> jax.Array:
    """CrowdNav++'s social force (crowd_nav/policy/social_force.py), every agent (A, 2): its
    velocity changed in one step by KI (v_pref towards the goal - velocity) and by each of
    `others` (O, 2) (radii (O,); the agents themselves first, then anyone else they see)
    pushing A exp((r_i + r_j - d_ij) / B) along their offset, then capped at v_pref."""
    to_goal = goal - position
    distance = jnp.linalg.norm(to_goal, axis=-1, keepdims=True)
    desired = to_goal / jnp.maximum(distance, 1e-9) * v_pref[:, None]
    pull = force.relocation_rate * (desired - velocity)
    offsets = position[:, None] - others[None]                           # [i, j] p_i - p_j
    apart = jnp.linalg.norm(offsets, axis=-1)
    strength = force.strength * jnp.exp(
        (radius[:, None] + others_radius[None] - apart) / force.range)
    # An agent's own offset is zero, so it does not push itself.
    push = jnp.sum((strength / jnp.maximum(apart, 1e-9))[..., None] * offsets, axis=1)
    velocity = velocity + (pull + push) * step_s
    speed = jnp.linalg.norm(velocity, axis=-1, keepdims=True)
    return jnp.where(speed > v_pref[:, None],
                     velocity / jnp.maximum(speed, 1e-9) * v_pref[:, None], velocity)
