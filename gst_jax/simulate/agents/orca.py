"""ORCA (van den Berg, Guy, Lin and Manocha 2011) inside jit: each agent's new velocity.

The algorithm of the RVO2 library, which CrowdNav++'s humans run, for agents without
obstacles. Each of an agent's neighbours (the `max_neighbours` nearest within
`neighbour_dist`, nearest first) gives a half-plane of velocities, the agent's share of
avoiding it for `time_horizon` seconds: a line (point, direction) whose left side is allowed.
The new velocity is the one closest to the preferred velocity inside every half-plane and the
disc of `max_speed` (a 2-D linear program solved incrementally, line by line); when they
leave nothing, the one that violates the worst half-plane least (the 3-D program RVO2 falls
back to).

Here every loop has a fixed length, the number of lines M, so that the solver jits and vmaps
over agents and episodes: a line that is absent (fewer neighbours) is skipped as if it were
not in the list, and each 1-D program over a line is one vectorised pass over the lines
before it. The result is that of RVO2's sequential code (tests/test_orca.py checks it against
a plain-Python transcription of the algorithm, gst_jax/testing/orca_reference.py).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

# RVO2's threshold under which two lines count as parallel.
PARALLEL = 1e-5


class Lines(NamedTuple):
    """M half-planes of velocities: the left of `direction` (unit) through `point`.

    point, direction: (..., M, 2); present: (..., M) which of them take part.
    """

    point: jax.Array
    direction: jax.Array
    present: jax.Array


class OrcaParams(NamedTuple):
    """An agent's ORCA settings (RVO2's names): seconds ahead within which collisions are
    avoided, neighbours considered, and how far away they may be."""

    time_horizon: float | jax.Array = 5.0       # arrays where traced (an episode's own)
    max_neighbours: int = 10
    neighbour_dist: float | jax.Array = 10.0


def det(a: jax.Array, b: jax.Array) -> jax.Array:
    """The 2-D cross product a_x b_y - a_y b_x over the last axis."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _normalized(v: jax.Array) -> jax.Array:
    return v / jnp.sqrt(jnp.maximum(jnp.sum(v * v, -1, keepdims=True), 1e-30))


def avoidance_line(relative_position: jax.Array, relative_velocity: jax.Array,
                   combined_radius: jax.Array, velocity: jax.Array,
                   time_horizon: float | jax.Array, step_s: float
                   ) -> tuple[jax.Array, jax.Array]:
    """The ORCA half-plane of one neighbour (vectorised over any leading axes): its point and
    direction. relative_position = p_j - p_i, relative_velocity = v_i - v_j, velocity = v_i.

    Apart, the velocity obstacle is a cone truncated at the disc of radius
    combined_radius / time_horizon; u is the smallest change of the relative velocity that
    takes it out, through the disc or across a leg. Overlapping already, the obstacle is the
    disc that separates the two within one step. Each agent takes half of u.
    """
    distance_sq = jnp.sum(relative_position ** 2, -1)
    radius_sq = combined_radius ** 2
    apart = distance_sq > radius_sq
    # Apart: w from the centre of the cut-off disc to the relative velocity.
    w = relative_velocity - relative_position / time_horizon
    w_length_sq = jnp.sum(w ** 2, -1)
    along = jnp.sum(w * relative_position, -1)
    through_disc = (along < 0) & (along ** 2 > radius_sq * w_length_sq)
    # Overlapping: the disc of one step's separation instead.
    w = jnp.where(apart[..., None], w, relative_velocity - relative_position / step_s)
    w_length = jnp.sqrt(jnp.maximum(jnp.sum(w ** 2, -1), 1e-30))
    unit_w = w / w_length[..., None]
    disc_radius = combined_radius / jnp.where(apart, time_horizon, step_s)
    disc_direction = jnp.stack([unit_w[..., 1], -unit_w[..., 0]], -1)
    disc_u = (disc_radius - w_length)[..., None] * unit_w
    # Across a leg: the left one when w lies left of the relative position, else the right.
    leg = jnp.sqrt(jnp.maximum(distance_sq - radius_sq, 0.0))
    x, y = relative_position[..., 0], relative_position[..., 1]
    left = jnp.stack([x * leg - y * combined_radius, x * combined_radius + y * leg], -1)
    right = -jnp.stack([x * leg + y * combined_radius, -x * combined_radius + y * leg], -1)
    leg_direction = jnp.where((det(relative_position, w) > 0)[..., None], left, right)
    leg_direction = leg_direction / jnp.maximum(distance_sq, 1e-30)[..., None]
    leg_u = (jnp.sum(relative_velocity * leg_direction, -1)[..., None] * leg_direction
             - relative_velocity)
    on_disc = (~apart | through_disc)[..., None]
    direction = jnp.where(on_disc, disc_direction, leg_direction)
    u = jnp.where(on_disc, disc_u, leg_u)
    return velocity + 0.5 * u, direction


def _along_line(lines: Lines, k: jax.Array, radius: jax.Array, optimum: jax.Array,
                optimise_direction: jax.Array, before: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The 1-D program on line k (RVO2's linearProgram1): the point of line k inside the
    speed disc and the half-planes `before` (M,) closest to `optimum`, or furthest in its
    direction when `optimise_direction`. Returns (feasible, that point)."""
    point, direction = lines.point[k], lines.direction[k]
    along = point @ direction
    discriminant = along ** 2 + radius ** 2 - point @ point
    root = jnp.sqrt(jnp.maximum(discriminant, 0.0))
    t_left, t_right = -along - root, -along + root
    denominator = det(direction, lines.direction)                           # (M,)
    numerator = det(lines.direction, point - lines.point)
    parallel = jnp.abs(denominator) <= PARALLEL
    t = numerator / jnp.where(parallel, 1.0, denominator)
    bounding = before & ~parallel
    t_right = jnp.minimum(t_right, jnp.min(jnp.where(bounding & (denominator >= 0), t, jnp.inf)))
    t_left = jnp.maximum(t_left, jnp.max(jnp.where(bounding & (denominator < 0), t, -jnp.inf)))
    feasible = ((discriminant >= 0) & ~jnp.any(before & parallel & (numerator < 0))
                & (t_left <= t_right))
    t = jnp.where(optimise_direction,
                  jnp.where(optimum @ direction > 0, t_right, t_left),
                  jnp.clip(direction @ (optimum - point), t_left, t_right))
    return feasible, point + t * direction


def solve_2d(lines: Lines, radius: jax.Array, optimum: jax.Array,
             optimise_direction: jax.Array | bool = False,
             count: jax.Array | int | None = None) -> tuple[jax.Array, jax.Array]:
    """The 2-D program (RVO2's linearProgram2): the velocity in every half-plane and the disc
    of `radius` closest to `optimum` (or furthest along it, with `optimise_direction`).
    Returns (velocity (2,), the first line that left nothing, M if none): on failure the
    velocity is the one found before that line. `count`: only the first lines matter (the
    others are absent), so the loop stops there."""
    num_lines = lines.point.shape[-2]
    optimise_direction = jnp.asarray(optimise_direction)
    speed_sq = optimum @ optimum
    clipped = jnp.where(speed_sq > radius ** 2, optimum * radius / jnp.sqrt(
        jnp.maximum(speed_sq, 1e-30)), optimum)
    start = jnp.where(optimise_direction, optimum * radius, clipped)
    order = jnp.arange(num_lines)

    def line(k, carry):
        velocity, failed_at = carry
        violated = (lines.present[k] & (failed_at == num_lines)
                    & (det(lines.direction[k], lines.point[k] - velocity) > 0))
        feasible, on_line = _along_line(lines, k, radius, optimum, optimise_direction,
                                        lines.present & (order < k))
        velocity = jnp.where(violated & feasible, on_line, velocity)
        return velocity, jnp.where(violated & ~feasible, k, failed_at)

    return jax.lax.fori_loop(0, num_lines if count is None else count, line,
                             (start, jnp.asarray(num_lines)))


def solve_3d(lines: Lines, first_failed: jax.Array, radius: jax.Array,
             velocity: jax.Array) -> jax.Array:
    """RVO2's linearProgram3, for when the half-planes leave no velocity: from line
    `first_failed` on, the velocity that minimises the largest violation (distance to the
    wrong side of a line), found line by line as a 2-D program on the bisectors of that line
    and each before it (so the i-th program loops over i lines only)."""
    num_lines = lines.point.shape[-2]
    order = jnp.arange(num_lines)

    def line(i, carry):
        velocity, violation = carry
        point, direction = lines.point[i], lines.direction[i]
        worse = (lines.present[i] & (i >= first_failed)
                 & (det(direction, point - velocity) > violation))
        # Lines of equal violation of line i and each earlier line j.
        crossing = det(direction, lines.direction)                            # (M,)
        parallel = jnp.abs(crossing) <= PARALLEL
        same_way = lines.direction @ direction > 0
        bisector_point = jnp.where(
            parallel[:, None], 0.5 * (point + lines.point),
            point + (det(lines.direction, point - lines.point)
                     / jnp.where(parallel, 1.0, crossing))[:, None] * direction)
        bisectors = Lines(bisector_point, _normalized(lines.direction - direction),
                          lines.present & (order < i) & ~(parallel & same_way))
        outward = jnp.stack([-direction[1], direction[0]])
        candidate, failed_at = solve_2d(bisectors, radius, outward, True, count=i)
        # RVO2 keeps the velocity it had if this fails, which it can only by rounding.
        velocity = jnp.where(worse & (failed_at == num_lines), candidate, velocity)
        violation = jnp.where(worse, det(direction, point - velocity), violation)
        return velocity, violation

    return jax.lax.fori_loop(0, num_lines, line,
                             (velocity, jnp.zeros((), velocity.dtype)))[0]


def new_velocity(lines: Lines, max_speed: jax.Array, preferred: jax.Array) -> jax.Array:
    """The velocity ORCA chooses (2,) given an agent's half-planes, maximum speed and
    preferred velocity."""
    velocity, failed_at = solve_2d(lines, max_speed, preferred)
    return solve_3d(lines, failed_at, max_speed, velocity)


def orca_velocities(position: jax.Array, velocity: jax.Array, radius: jax.Array,
                    max_speed: jax.Array, preferred: jax.Array, present: jax.Array,
                    params: OrcaParams, step_s: float) -> jax.Array:
    """Every agent's ORCA velocity for one step, (A, 2).

    position, velocity, preferred: (A, 2); radius, max_speed: (A,); present: (A,) which agents
    exist (the others neither move by this nor are avoided). Each agent avoids its
    `params.max_neighbours` nearest present agents closer than `params.neighbour_dist`,
    nearest first, assuming they take their half of the avoidance.
    """
    num_agents = position.shape[0]
    count = min(params.max_neighbours, num_agents - 1)
    offsets = position[None, :, :] - position[:, None, :]                     # [i, j] p_j - p_i
    distance_sq = jnp.sum(offsets ** 2, -1)
    candidate = (present[None, :] & ~jnp.eye(num_agents, dtype=bool)
                 & (distance_sq < params.neighbour_dist ** 2))
    # Nearest first; lax.top_k keeps the lower index first among equals.
    _, neighbours = jax.lax.top_k(jnp.where(candidate, -distance_sq, -jnp.inf), count)

    def one(i, neighbours):
        j = neighbours
        point, direction = avoidance_line(offsets[i, j], velocity[i] - velocity[j],
                                          radius[i] + radius[j], velocity[i],
                                          params.time_horizon, step_s)
        lines = Lines(point, direction, candidate[i, j])
        return new_velocity(lines, max_speed[i], preferred[i])

    chosen = jax.vmap(one)(jnp.arange(num_agents), neighbours)
    return jnp.where(present[:, None], chosen, 0.0)
