"""experiments/accuracy_needed.py and truth_knows.py (issue 90, where the truth's margin goes):
the truth moved toward constant velocity, and the truth's rollout with hidden quantities
estimated."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from accuracy_needed import TruthTowardCV
from gst_jax.simulate.crowdnav.environment import CONSTANT_VELOCITY, CrowdNav
from truth_knows import HIDDEN, estimated

# Three people walking east at 1 m/s in steps of 0.25 s; a made-up truth that stands still.
HISTORY = jnp.stack([jnp.stack([0.25 * jnp.arange(5.0), jnp.full(5, y)], -1)
                     for y in (0.0, 2.0, 4.0)])
DETECTED = jnp.ones((3, 5)).at[2, -2].set(0.0)
STANDING = jnp.broadcast_to(HISTORY[:, -1:], (3, 5, 2))


def test_truth_toward_cv_moves_the_given_share_of_the_way():
    cv = 1.0 + 0.25 * jnp.arange(1, 6)
    for weight in (0.0, 0.25, 1.0):
        futures, predicted = TruthTowardCV(weight=weight).predict(
            None, None, HISTORY, DETECTED, truth=lambda: STANDING)
        np.testing.assert_allclose(futures[0, :, 0, 0], 1.0 + weight * (cv - 1.0), atol=1e-6)
        np.testing.assert_allclose(futures[0, :, 0, 1], 0.0, atol=1e-6)
        # The third person was missed a step ago: no displacement, not predicted.
        assert predicted.tolist() == [True, True, False]


def test_estimates_replace_only_what_they_name():
    env, params = CrowdNav.with_predictor(CONSTANT_VELOCITY, 4, shift="speed")
    _, state = env.reset(jax.random.key(0), params)
    for _ in range(3):
        _, state, *_ = env.step_env(jax.random.key(1), state, jnp.zeros(2), params)
    unchanged = estimated(env, state, params, ())
    np.testing.assert_array_equal(env._truth(unchanged, params), env._truth(state, params))
    guessed = estimated(env, state, params, ("goal", "radius"))
    np.testing.assert_allclose(guessed.human_radius, 0.4)
    np.testing.assert_array_equal(guessed.human_v_pref, state.human_v_pref)
    # The goal lies ahead along the last observed step.
    positions = state.tracks.positions
    step = positions[:, -1] - positions[:, -2]
    ahead = guessed.human_goal - state.human_position
    cosine = jnp.sum(ahead * step, -1) / (jnp.linalg.norm(ahead, axis=-1)
                                          * jnp.linalg.norm(step, axis=-1))
    seen = (state.tracks.detected[:, -2:] > 0).all(-1)
    np.testing.assert_allclose(cosine[seen], 1.0, atol=1e-5)
    assert set(HIDDEN) == {"goal", "preferred speed", "radius", "unseen", "clock"}
