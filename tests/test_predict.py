"""The prediction API: make_batch from NaN-marked observations, jitted predict, compiles."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

import gst_jax
from gst_jax import compiles
from gst_jax.compiles import count_compiles
from gst_jax.model import Controls
from gst_jax.rollout import rollout

CONFIG = gst_jax.ModelConfig()
K = 3


def observations(num_pedestrians: int, seed: int = 0) -> np.ndarray:
    """(1, 8, N, 2) walkers; the last one appears at step 6, the first is lost at step 7."""
    rng = np.random.default_rng(seed)
    xy = np.cumsum(rng.normal(0.4, 0.05, (1, 8, num_pedestrians, 2)), axis=1)
    xy += rng.uniform(-4, 4, (1, 1, num_pedestrians, 2))
    xy[0, :6, -1] = np.nan
    xy[0, 7, 0] = np.nan
    return xy


def test_predict_from_nan_marked_observations():
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    predict = gst_jax.make_predict(CONFIG, num_samples=K)
    xy = observations(5)
    prediction = predict(params, jax.random.key(1), gst_jax.make_batch(xy))
    assert prediction.positions.shape == (K, 1, 12, 8, 2)
    assert prediction.sampled_adjacency.shape == (K, 1, 19, 8, 9)
    assert prediction.edge_probs.shape == (K, 1, 19, 8, 1, 9)
    np.testing.assert_array_equal(prediction.predicted_mask[0], [0, 1, 1, 1, 1, 0, 0, 0])
    positions = np.asarray(prediction.positions)
    assert np.all(np.isfinite(positions[:, 0, :, 1:5]))
    # Not predicted (pedestrian 0 was lost at the last step; 5-7 are padding): NaN, which no
    # planner can mistake for a position.
    assert np.all(np.isnan(positions[:, 0, :, [0, 5, 6, 7]]))
    # Positions continue from the last observation by the predicted displacements.
    np.testing.assert_allclose(positions[:, 0, 0, 1:5],
                               xy[0, 7, 1:5] + prediction.displacements[:, 0, 0, 1:5], atol=1e-5)
    # n = 1: every predicted target picks exactly one neighbour (possibly the ghost).
    np.testing.assert_allclose(np.asarray(prediction.sampled_adjacency)[:, 0, 8:, 1:5].sum(-1), 1.0)
    # K samples are different draws of the graph.
    assert not np.array_equal(prediction.sampled_adjacency[0], prediction.sampled_adjacency[1])


def test_samples_share_the_observation_pass_without_changing_them():
    """predict computes the observed edge probabilities once; each sample equals a rollout
    that computes them itself."""
    config = gst_jax.ModelConfig(output="gaussian")
    params = gst_jax.init_params(config, jax.random.key(0))
    batch = gst_jax.make_batch(observations(6))
    key = jax.random.key(3)
    prediction = gst_jax.make_predict(config, num_samples=K)(params, key, batch)
    controls = Controls.from_config(config)
    alone_rollout = jax.jit(lambda sample_key: rollout(params, sample_key, batch, config,
                                                       controls, hard=True, deterministic=True))
    for k, sample_key in enumerate(jax.random.split(key, K)):
        alone = alone_rollout(sample_key)
        np.testing.assert_allclose(prediction.displacements[k], alone.displacements, atol=1e-5)
        np.testing.assert_allclose(prediction.edge_probs[k], alone.edge_probs, atol=1e-6)


def test_predict_compiles_once_per_bucket():
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    predict = gst_jax.make_predict(CONFIG, num_samples=K, with_graph=False)
    keys = [jax.random.key(seed) for seed in range(5)]

    def run(num_pedestrians: int, seed: int):
        out = predict(params, keys[seed], gst_jax.make_batch(observations(num_pedestrians, seed)))
        return jax.block_until_ready(out)

    with count_compiles() as first_two_buckets:
        assert run(3, 0).positions.shape[3] == 8
        assert run(9, 1).positions.shape[3] == 16
    assert first_two_buckets.count >= 2
    with count_compiles() as same_buckets:                     # buckets 8 and 16 again
        for num_pedestrians, seed in [(5, 2), (8, 3), (12, 4), (3, 0), (16, 1)]:
            run(num_pedestrians, seed)
    assert same_buckets.count == 0
    with count_compiles() as new_bucket:                       # the counter sees a new shape
        assert run(20, 2).positions.shape[3] == 24
    assert new_bucket.count >= 1


def test_compiling_near_the_kernel_s_limit_on_memory_maps_warns_once(monkeypatch):
    held = iter([40_000, 50_000, 60_000])               # maps after each compile; limit 65530
    monkeypatch.setattr(compiles, "memory_maps", lambda: (next(held), 65530))
    triple = jax.jit(lambda x: 3 * x)
    with count_compiles() as counter:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            triple(np.ones(2))                          # 61 % of the limit: quiet
        with pytest.warns(UserWarning, match=r"holds 50000 memory maps of the 65530 .* "
                                             r"sudo sysctl -w vm.max_map_count=262144"):
            triple(np.ones(3))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            triple(np.ones(4))                          # said once
    assert counter.count == 3


def test_memory_maps_are_read_from_the_kernel_on_linux():
    maps = compiles.memory_maps()
    if maps is None:
        pytest.skip("not Linux")
    held, limit = maps
    assert 0 < held < limit
