"""A planner's safety margin calibrated online to a target rate of near misses (issue 90,
part 4b: conformal decision theory): on a synthetic stream the rate lands on the target within
the deterministic bound, from a margin too small or too large."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax.simulate.crowdnav.environment import UNDETECTED, Observation
from gst_jax.simulate.crowdnav.planner import DecisionCalibration, SamplingMPC

STEPS = 4000


def near_misses(calibration: DecisionCalibration, start: float, seed: int) -> np.ndarray:
    """A stream whose near misses come with probability 0.8 exp(-margin / 0.15), drifting:
    from step 2000 the crowd is twice as dangerous (the calibration must follow)."""
    uniforms = jax.random.uniform(jax.random.key(seed), (STEPS,))
    danger = jnp.where(jnp.arange(STEPS) < STEPS // 2, 0.15, 0.3)

    def step(margin, inputs):
        u, scale = inputs
        miss = (u < 0.8 * jnp.exp(-margin / scale)).astype(jnp.float32)
        return calibration.update(margin, miss), miss

    _, misses = jax.lax.scan(step, jnp.asarray(start), (uniforms, danger))
    return np.asarray(misses)


@pytest.mark.parametrize("start", [0.0, 1.0])
def test_the_rate_of_near_misses_lands_on_the_target(start):
    calibration = DecisionCalibration(target_rate=0.1, step=0.05, max_margin=1.0)
    misses = near_misses(calibration, start, seed=3)
    bound = (calibration.max_margin + calibration.step) / (calibration.step * STEPS)
    assert abs(misses.mean() - 0.1) <= bound                     # 0.00525 here
    assert abs(misses[STEPS // 2:].mean() - 0.1) <= 2 * bound    # after the drift too
    uncalibrated = near_misses(DecisionCalibration(step=0.0), start, seed=3).mean()
    assert abs(uncalibrated - 0.1) > 0.05                         # a fixed margin misses it


def test_a_near_miss_is_a_detected_human_within_reach():
    calibration = DecisionCalibration(near=1.0)
    edges = jnp.full((3, 12), UNDETECTED).at[0, :2].set(jnp.array([0.9, 0.0]))
    obs = Observation(jnp.zeros(7), jnp.zeros(2), edges, jnp.ones(3, bool), jnp.asarray(1.0),
                      jnp.zeros((3, 5)))
    assert float(calibration.near_miss(obs)) == 1.0
    assert float(calibration.near_miss(obs._replace(
        spatial_edges=edges.at[0, :2].set(jnp.array([1.1, 0.0]))))) == 0.0


def test_the_margin_widens_the_planner_s_berth():
    """The same observation, a human 1 m away on the way to the goal: with a margin the
    chosen first step keeps farther from them."""
    edges = jnp.full((1, 12), UNDETECTED).at[0].set(jnp.tile(jnp.array([0.0, 1.0]), 6))
    robot = jnp.array([0.0, 0.0, 0.3, 0.0, 5.0, 1.0, 1.57])
    obs = Observation(robot, jnp.zeros(2), edges, jnp.ones(1, bool), jnp.asarray(1.0),
                      jnp.zeros((1, 5)))
    plain = SamplingMPC()
    calibrated = SamplingMPC(calibration=DecisionCalibration(max_margin=1.0))
    key = jax.random.key(0)
    _, plain_state = plain(key, plain.init(), obs)
    wide = calibrated.init()._replace(margin=jnp.asarray(0.8))
    _, wide_state = calibrated(key, wide, obs)
    clearance = lambda state: float(jnp.min(jnp.linalg.norm(
        jnp.cumsum(state.plan, axis=0) * 0.25 - jnp.array([0.0, 1.0]), axis=-1)))
    assert float(wide_state.margin) > 0.8                        # a near miss: it grew
    assert clearance(wide_state) > clearance(plain_state)
