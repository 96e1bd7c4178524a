"""A plain-Python ORCA for one agent, loops and early returns as in the RVO2 library's
algorithm (van den Berg et al. 2011; RVO2's Agent::computeNewVelocity and its three linear
programs), float64, no jax: what tests/test_orca.py holds gst_jax.simulate.agents.orca to.

Lines are lists of (point, direction) pairs of 2-tuples; velocities are 2-tuples.
"""

from __future__ import annotations

import math

PARALLEL = 1e-5


def _det(a, b):
    return a[0] * b[1] - a[1] * b[0]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1]


def _add(a, b, scale=1.0):
    return (a[0] + scale * b[0], a[1] + scale * b[1])


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1])


def _scaled(a, scale):
    return (a[0] * scale, a[1] * scale)


def _unit(a):
    return _scaled(a, 1.0 / math.hypot(*a))


def avoidance_line(relative_position, relative_velocity, combined_radius, velocity,
                   time_horizon, step_s):
    """One neighbour's half-plane: (point, direction)."""
    distance_sq = _dot(relative_position, relative_position)
    radius_sq = combined_radius ** 2
    if distance_sq > radius_sq:
        w = _sub(relative_velocity, _scaled(relative_position, 1.0 / time_horizon))
        w_length_sq = _dot(w, w)
        along = _dot(w, relative_position)
        if along < 0 and along ** 2 > radius_sq * w_length_sq:
            w_length = math.sqrt(w_length_sq)
            unit_w = _scaled(w, 1.0 / w_length)
            direction = (unit_w[1], -unit_w[0])
            u = _scaled(unit_w, combined_radius / time_horizon - w_length)
        else:
            leg = math.sqrt(distance_sq - radius_sq)
            x, y = relative_position
            if _det(relative_position, w) > 0:
                direction = _scaled((x * leg - y * combined_radius,
                                     x * combined_radius + y * leg), 1.0 / distance_sq)
            else:
                direction = _scaled((x * leg + y * combined_radius,
                                     -x * combined_radius + y * leg), -1.0 / distance_sq)
            u = _sub(_scaled(direction, _dot(relative_velocity, direction)), relative_velocity)
    else:
        w = _sub(relative_velocity, _scaled(relative_position, 1.0 / step_s))
        w_length = math.hypot(*w)
        unit_w = _scaled(w, 1.0 / w_length)
        direction = (unit_w[1], -unit_w[0])
        u = _scaled(unit_w, combined_radius / step_s - w_length)
    return _add(velocity, u, 0.5), direction


def program_1d(lines, k, radius, optimum, optimise_direction):
    """(feasible, velocity) on line k against lines 0..k-1 and the disc."""
    point, direction = lines[k]
    along = _dot(point, direction)
    discriminant = along ** 2 + radius ** 2 - _dot(point, point)
    if discriminant < 0:
        return False, None
    root = math.sqrt(discriminant)
    t_left, t_right = -along - root, -along + root
    for other_point, other_direction in lines[:k]:
        denominator = _det(direction, other_direction)
        numerator = _det(other_direction, _sub(point, other_point))
        if abs(denominator) <= PARALLEL:
            if numerator < 0:
                return False, None
            continue
        t = numerator / denominator
        if denominator >= 0:
            t_right = min(t_right, t)
        else:
            t_left = max(t_left, t)
        if t_left > t_right:
            return False, None
    if optimise_direction:
        t = t_right if _dot(optimum, direction) > 0 else t_left
    else:
        t = min(max(_dot(direction, _sub(optimum, point)), t_left), t_right)
    return True, _add(point, direction, t)


def program_2d(lines, radius, optimum, optimise_direction=False):
    """(index of the first line that failed or len(lines), velocity)."""
    if optimise_direction:
        velocity = _scaled(optimum, radius)
    elif _dot(optimum, optimum) > radius ** 2:
        velocity = _scaled(_unit(optimum), radius)
    else:
        velocity = optimum
    for k, (point, direction) in enumerate(lines):
        if _det(direction, _sub(point, velocity)) > 0:
            feasible, on_line = program_1d(lines, k, radius, optimum, optimise_direction)
            if not feasible:
                return k, velocity
            velocity = on_line
    return len(lines), velocity


def program_3d(lines, first_failed, radius, velocity):
    violation = 0.0
    for i in range(first_failed, len(lines)):
        point, direction = lines[i]
        if _det(direction, _sub(point, velocity)) > violation:
            bisectors = []
            for other_point, other_direction in lines[:i]:
                crossing = _det(direction, other_direction)
                if abs(crossing) <= PARALLEL:
                    if _dot(direction, other_direction) > 0:
                        continue
                    bisector_point = _scaled(_add(point, other_point), 0.5)
                else:
                    bisector_point = _add(point, direction, _det(
                        other_direction, _sub(point, other_point)) / crossing)
                bisectors.append((bisector_point, _unit(_sub(other_direction, direction))))
            failed, candidate = program_2d(bisectors, radius, (-direction[1], direction[0]),
                                           True)
            if failed == len(bisectors):
                velocity = candidate
            violation = _det(direction, _sub(point, velocity))
    return velocity


def new_velocity(lines, max_speed, preferred):
    failed, velocity = program_2d(lines, max_speed, preferred)
    if failed < len(lines):
        velocity = program_3d(lines, failed, max_speed, velocity)
    return velocity


def orca_velocity(i, positions, velocities, radii, max_speed, preferred, time_horizon,
                  max_neighbours, neighbour_dist, step_s):
    """Agent i's new velocity among agents given as lists of 2-tuples and floats."""
    within = []
    for j, position in enumerate(positions):
        if j == i:
            continue
        offset = _sub(position, positions[i])
        distance_sq = _dot(offset, offset)
        if distance_sq < neighbour_dist ** 2:
            within.append((distance_sq, j))
    nearby = [j for _, j in sorted(within)][:max_neighbours]
    lines = [avoidance_line(_sub(positions[j], positions[i]), _sub(velocities[i], velocities[j]),
                            radii[i] + radii[j], velocities[i], time_horizon, step_s)
             for j in nearby]
    return new_velocity(lines, max_speed, preferred)
