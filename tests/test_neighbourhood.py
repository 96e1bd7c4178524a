"""Candidate neighbourhoods (`ModelConfig.candidates`, docs/MODEL.md 2.4): each target's k
nearest people as its only neighbours, the exact model when k covers everyone."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gst_jax
from gst_jax.graph import edge_features
from gst_jax.model.selector import nearest_candidates
from gst_jax.rollout import observed_edge_probabilities


def _walkers(num_pedestrians: int, steps: int = 8, seed: int = 0) -> np.ndarray:
    """(2, steps, N, 2) observed positions: random walks spread over 10 m, one person missed."""
    rng = np.random.default_rng(seed)
    positions = (rng.normal(size=(2, steps, num_pedestrians, 2)).cumsum(1) * 0.3
                 + rng.uniform(-5, 5, size=(2, 1, num_pedestrians, 2)))
    positions[0, :3, 2] = np.nan
    return positions


def test_the_candidates_are_the_nearest_valid_people_self_first():
    xy = jnp.array([[0.0, 0.0], [3.0, 0.0], [1.0, 0.0], [0.0, 2.0], [0.5, 0.0]])
    mask = jnp.array([1.0, 1.0, 1.0, 1.0, 0.0])      # the nearest of all is not detected
    candidates = nearest_candidates(edge_features(xy, mask), mask, 3)
    np.testing.assert_array_equal(candidates[0], [0, 2, 3])
    np.testing.assert_array_equal(candidates[1], [1, 2, 0])


@pytest.mark.parametrize("pretrained", ["eth_d", "crowdnav_sim"])
def test_candidates_covering_everyone_predict_as_the_exact_model(pretrained):
    config, params = gst_jax.load_pretrained(pretrained)
    batch = gst_jax.make_batch(_walkers(12, config.obs_len), grid=config.grid)
    key = jax.random.key(3)
    exact = gst_jax.make_predict(config, 4)(params, key, batch)
    covering = gst_jax.make_predict(dataclasses.replace(config, candidates=12), 4)(
        params, key, batch)
    np.testing.assert_allclose(covering.positions, exact.positions, rtol=0, atol=1e-4)


def test_a_neighbourhood_gives_no_probability_outside_the_candidates():
    config, params = gst_jax.load_pretrained("eth_d")
    batch = gst_jax.make_batch(_walkers(12))
    nearest = dataclasses.replace(config, candidates=4)
    controls = gst_jax.Controls.from_config(nearest)
    probs = jax.jit(observed_edge_probabilities, static_argnums=2)(
        params, batch, nearest, controls)                                  # (B, T, N, G, N+1)
    active = probs[..., :config.num_edge_heads, :]
    np.testing.assert_allclose(active.sum(-1)[batch.node_mask[..., None] > 0], 1.0, atol=1e-5)
    outside = (active[..., :-1] > 0).sum(-1)             # people with probability, per head
    assert int(outside.max()) <= 4


def test_a_model_trains_through_a_neighbourhood():
    config, params = gst_jax.load_pretrained("eth_d")
    nearest = dataclasses.replace(config, candidates=3)
    batch = gst_jax.make_batch(_walkers(8))
    predict = gst_jax.make_predict(nearest, 1, with_graph=False)
    gradient = jax.grad(lambda p: jnp.nanmean(predict(p, jax.random.key(0), batch).positions))(
        params)
    leaves = jax.tree_util.tree_leaves(gradient)
    assert all(bool(jnp.isfinite(g).all()) for g in leaves)
    assert any(float(jnp.abs(g).max()) > 0 for g in leaves)


def test_evaluate_predicts_with_the_candidates_it_is_given(capsys, tmp_path):
    """`evaluate --candidates K` scores the model with a neighbourhood: on windows of 22 and
    30 people a neighbourhood of 2 (each target and its nearest) predicts otherwise than the
    exact model with the same draws, so its errors differ, and `--candidates 0` is the exact
    model. It writes nothing (its work directory's records stay the exact model's)."""
    from gst_jax.evaluate import main

    def evaluated(*flags: str) -> dict:
        main(["pretrained:eth_d", *flags, "--max-windows", "2", "--samples", "2", "--no-kde",
              "--json", "--workdir", str(tmp_path)])
        return json.loads(capsys.readouterr().out)

    nearest = evaluated("--candidates", "2")
    assert 0 < nearest["aoe"] < 5
    assert not any(tmp_path.iterdir())
    exact = evaluated("--candidates", "0")
    assert nearest["pedestrians"] == exact["pedestrians"] > 0
    assert abs(nearest["aoe"] - exact["aoe"]) > 1e-3
    assert nearest["cv_aoe"] == exact["cv_aoe"]       # the same pedestrians, the same truth
