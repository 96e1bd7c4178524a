"""ORCA inside jit (gst_jax.simulate.agents.orca) against the RVO2 algorithm: a plain-Python
transcription of its sequential code on random crowds, and cases whose answer follows from
the algorithm by hand."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax.simulate.agents.orca import (
    Lines,
    OrcaParams,
    det,
    new_velocity,
    orca_velocities,
    solve_2d,
)
from gst_jax.testing import orca_reference

STEP_S = 0.25
PARAMS = OrcaParams(time_horizon=5.0, max_neighbours=10, neighbour_dist=10.0)
# One program per crowd size and precision, not one eager compile per operation.
ORCA = jax.jit(orca_velocities, static_argnames=("params", "step_s"))


def _orca(position, velocity, preferred, radius=0.31, max_speed=1.0, present=None,
          params=PARAMS):
    """Every agent's ORCA velocity, in float32 or, under jax.enable_x64, float64."""
    count = len(position)
    present = np.ones(count, bool) if present is None else np.asarray(present)
    as_array = lambda a: jnp.asarray(np.asarray(a, np.float64))
    return np.asarray(ORCA(
        as_array(position), as_array(velocity), jnp.full(count, radius),
        jnp.full(count, max_speed), as_array(preferred), jnp.asarray(present), params, STEP_S))


def _reference(position, velocity, preferred, radius=0.31, max_speed=1.0, params=PARAMS):
    as_tuples = lambda a: [tuple(map(float, row)) for row in np.asarray(a, np.float64)]
    position, velocity, preferred = map(as_tuples, (position, velocity, preferred))
    return np.array([orca_reference.orca_velocity(
        i, position, velocity, [radius] * len(position), max_speed, preferred[i],
        params.time_horizon, params.max_neighbours, params.neighbour_dist, STEP_S)
        for i in range(len(position))])


@pytest.mark.parametrize("spread", [6.0, 2.0, 1.0])   # sparse; crowded; overlapping discs
def test_every_agent_chooses_what_rvo2s_algorithm_chooses(spread):
    # In float64, as the reference: the programs branch on signs (is a line violated, is a
    # 1-D program feasible), which float32 (RVO2's own precision) can flip at a border.
    rng = np.random.default_rng(int(spread * 10))
    for _ in range(4):
        count = 14
        position = rng.uniform(-spread, spread, (count, 2))
        velocity = rng.normal(0, 0.7, (count, 2))
        goal = rng.uniform(-6, 6, (count, 2))
        preferred = (goal - position) / np.maximum(
            np.linalg.norm(goal - position, axis=-1, keepdims=True), 1.0)
        with jax.enable_x64(True):
            ours = _orca(position, velocity, preferred)
        np.testing.assert_allclose(ours, _reference(position, velocity, preferred), atol=1e-9)


def test_crowded_agents_fall_back_to_the_least_violation():
    # Eight agents pressed into a disc smaller than themselves: no velocity satisfies every
    # half-plane, so the solver must take RVO2's 3-D program, and still agree with it.
    angle = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    position = 0.3 * np.stack([np.cos(angle), np.sin(angle)], -1)
    preferred = -position / 0.3                                   # everyone to the centre
    _, failed_at = solve_2d(_lines_of(position, preferred, agent=0), jnp.asarray(1.0),
                            jnp.asarray(preferred[0], jnp.float32))
    assert int(failed_at) < 7
    with jax.enable_x64(True):
        ours = _orca(position, preferred, preferred)
    np.testing.assert_allclose(ours, _reference(position, preferred, preferred), atol=1e-9)


def _lines_of(position, velocity, agent):
    others = [j for j in range(len(position)) if j != agent]
    pairs = [orca_reference.avoidance_line(tuple(position[j] - position[agent]),
                                           tuple(velocity[agent] - velocity[j]), 0.62,
                                           tuple(velocity[agent]), 5.0, STEP_S) for j in others]
    return Lines(jnp.asarray([p for p, _ in pairs], jnp.float32),
                 jnp.asarray([d for _, d in pairs], jnp.float32), jnp.ones(len(pairs), bool))


def test_alone_an_agent_walks_its_preferred_velocity_up_to_its_speed():
    chosen = _orca([[0, 0], [20, 0]], [[0, 0], [0, 0]], [[0.6, 0.0], [3.0, 4.0]])
    np.testing.assert_allclose(chosen, [[0.6, 0.0], [0.6, 0.8]], atol=1e-6)


def test_two_agents_head_on_share_the_avoidance_and_then_miss_each_other():
    # Symmetric: each turns by the same amount to its own side (reciprocity), and the new
    # relative velocity keeps them apart for the whole time horizon.
    position = np.array([[-2.0, 0.0], [2.0, 0.0]])
    velocity = np.array([[1.0, 0.0], [-1.0, 0.0]])
    chosen = _orca(position, velocity, velocity)
    np.testing.assert_allclose(chosen[0], -chosen[1], atol=1e-6)
    assert abs(chosen[0, 1]) > 0.05
    relative = chosen[0] - chosen[1]
    closest = np.abs(det(jnp.asarray(position[1] - position[0]), jnp.asarray(relative))) / (
        np.linalg.norm(relative))
    assert closest >= 0.62 - 1e-3


def test_a_neighbour_moving_away_changes_nothing_and_absent_agents_are_not_avoided():
    position = [[0.0, 0.0], [1.0, 0.0], [0.5, 0.0]]
    velocity = [[0.5, 0.0], [1.0, 0.0], [0.0, 0.0]]
    chosen = _orca(position, velocity, velocity, present=[True, True, False])
    np.testing.assert_allclose(chosen[0], [0.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(chosen[2], [0.0, 0.0])


def test_only_the_nearest_neighbours_within_range_count():
    # A far agent on a collision course is beyond neighbour_dist: ignored.
    position = [[0.0, 0.0], [0.0, 4.0]]
    velocity = [[0.0, 1.0], [0.0, -1.0]]
    near_sighted = OrcaParams(time_horizon=5.0, max_neighbours=10, neighbour_dist=3.0)
    np.testing.assert_allclose(_orca(position, velocity, velocity, params=near_sighted),
                               velocity, atol=1e-6)
    assert not np.allclose(_orca(position, velocity, velocity), velocity, atol=1e-3)


def test_the_chosen_velocity_lies_in_every_half_plane_when_some_velocity_does():
    rng = np.random.default_rng(7)
    position = rng.uniform(-5, 5, (10, 2))
    velocity = rng.normal(0, 0.5, (10, 2))
    lines = _lines_of(position, velocity, agent=0)
    chosen = new_velocity(lines, jnp.asarray(1.0), jnp.asarray(velocity[0], jnp.float32))
    assert np.all(np.asarray(det(lines.direction, lines.point - chosen)) <= 1e-4)
    assert float(jnp.linalg.norm(chosen)) <= 1.0 + 1e-5
    assert math.isfinite(float(chosen[0]))
