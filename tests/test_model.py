"""Model properties: Gumbel sampling, masking, padding and permutation, traced n, keys."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import graph, noise
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch, node_mask_from_positions
from gst_jax.gumbel import gumbel_softmax, sample_gumbel
from gst_jax.model import Controls, init_params
from gst_jax.model.layers import Dropout
from gst_jax.model.selector import group_to_head, head_totals
from gst_jax.rollout import RolloutNoise, rollout, rollout_with_noise
from gst_jax.testing.release import batch_loss

# One encoder layer: each layer masks and pads as the first does, and deeper programs only
# compile longer.
CONFIG = ModelConfig(num_edge_heads=4, max_edge_heads=16, encoder_layers=1)
INIT = jax.jit(init_params, static_argnums=0)
T, N = 20, 5


def scene_batch(positions: np.ndarray, position_mask: np.ndarray) -> SceneBatch:
    """(B, T, N, 2) positions and (B, T, N) validity -> SceneBatch."""
    position_mask = position_mask.astype(np.float32)
    return SceneBatch(positions=(positions * position_mask[..., None]).astype(np.float32),
                      position_mask=position_mask,
                      node_mask=node_mask_from_positions(position_mask),
                      scene_mask=np.ones(positions.shape[0], np.float32),
                      window_index=np.arange(positions.shape[0], dtype=np.int32))


@pytest.fixture(scope="module")
def walk():
    """One scene of N walkers; pedestrian 3 leaves after step 12, pedestrian 4 enters at 5."""
    rng = np.random.default_rng(0)
    steps = rng.normal(0.0, 0.1, (1, T, N, 2)) + np.array([0.4, 0.0])
    positions = np.cumsum(steps, axis=1) + rng.uniform(-3, 3, (1, 1, N, 2))
    mask = np.ones((1, T, N))
    mask[:, 13:, 3] = 0
    mask[:, :5, 4] = 0
    return positions, mask


@pytest.fixture(scope="module")
def params():
    return INIT(CONFIG, jax.random.key(0))


def random_noise(key, batch_size, num_nodes, config=CONFIG) -> RolloutNoise:
    shape = (num_nodes, config.head_slots, num_nodes + 1)
    k1, k2, k3 = jax.random.split(key, 3)
    return RolloutNoise(
        gumbel_obs=sample_gumbel(k1, (batch_size, config.obs_len) + shape),
        gumbel_pred=sample_gumbel(k2, (config.pred_len - 1, batch_size) + shape),
        normal=jax.random.normal(k3, (config.pred_len, batch_size, num_nodes, 2)))


def _scatter(g: jax.Array, num_nodes: int, order: np.ndarray) -> jax.Array:
    """g (..., n, G, n+1) -> (..., N, G, N+1) with target/neighbour k moved to slot order[k]."""
    small = g.shape[-3]
    columns = np.append(order, num_nodes)          # the ghost column stays last
    out = jnp.zeros(g.shape[:-3] + (num_nodes, g.shape[-2], num_nodes + 1), g.dtype)
    out = out.at[..., order, :, :].set(jnp.zeros(g.shape[:-3] + (small, g.shape[-2], num_nodes + 1))
                                       .at[..., columns].set(g))
    return out


def move_noise(noise: RolloutNoise, num_nodes: int, order: np.ndarray) -> RolloutNoise:
    normal = jnp.zeros(noise.normal.shape[:-2] + (num_nodes, 2)).at[..., order, :].set(noise.normal)
    return RolloutNoise(gumbel_obs=_scatter(noise.gumbel_obs, num_nodes, order),
                        gumbel_pred=_scatter(noise.gumbel_pred, num_nodes, order), normal=normal)


def move_batch(positions, mask, num_nodes, order):
    big_positions = np.zeros(positions.shape[:2] + (num_nodes, 2))
    big_mask = np.zeros(mask.shape[:2] + (num_nodes,))
    big_positions[:, :, order] = positions
    big_mask[:, :, order] = mask
    return scene_batch(big_positions, big_mask)


def run(params, batch, noise, *, hard=True, tau=0.5, config=CONFIG, n=None):
    controls = Controls.make(tau, config.num_edge_heads if n is None else n, config.ghost)
    return _jitted_rollout(params, batch, noise, controls, hard, config)


@functools.partial(jax.jit, static_argnums=(4, 5))
def _jitted_rollout(params, batch, noise, controls, hard, config):
    # One compile per (shape, hard, config): tau and n are traced, as in training.
    return rollout_with_noise(params, noise, batch, config, controls, hard=hard,
                              return_attention=True)


# --- building blocks -----------------------------------------------------------------------

def test_hard_gumbel_samples_are_one_hot_with_soft_gradients():
    log_probs = jnp.log(jnp.array([[0.2, 0.5, 0.3], [0.9, 0.05, 0.05]]))
    noise = sample_gumbel(jax.random.key(1), log_probs.shape)
    hard = gumbel_softmax(log_probs, noise, 0.5, hard=True)
    assert set(np.unique(hard)) <= {0.0, 1.0} and np.all(hard.sum(-1) == 1)
    weights = jnp.arange(3.0)
    grad_hard = jax.grad(
        lambda lp: jnp.sum(gumbel_softmax(lp, noise, 0.5, True) * weights))(log_probs)
    grad_soft = jax.grad(
        lambda lp: jnp.sum(gumbel_softmax(lp, noise, 0.5, False) * weights))(log_probs)
    np.testing.assert_allclose(grad_hard, grad_soft, atol=1e-6)
    assert np.abs(grad_soft).sum() > 0


def test_gumbel_noise_depends_only_on_the_key():
    a = sample_gumbel(jax.random.key(3), (4, 5))
    np.testing.assert_array_equal(a, sample_gumbel(jax.random.key(3), (4, 5)))
    assert not np.allclose(a, sample_gumbel(jax.random.key(4), (4, 5)))


def test_every_uniform_draw_gives_a_finite_normal():
    # The largest uniform, 1 - 2^-24, once rounded to 1 (an infinite normal, then NaN
    # predictions: a zara1 GST (P) training stopped on it at epoch 10).
    cells = jnp.array([0.0, 2.0 ** -24, 0.5, 1.0 - 2.0 ** -23, 1.0 - 2.0 ** -24], jnp.float32)
    draws = np.asarray(noise.standard_normal_quantile(cells))
    assert np.all(np.isfinite(draws)) and np.all(np.diff(draws) > 0)
    assert -5.6 < draws[0] < -5.2 and abs(draws[2]) < 1e-6 and 5.2 < draws[-1] < 5.6
    sample = np.asarray(noise.normal(jax.random.key(0), (100_000,)))
    assert abs(sample.mean()) < 0.02 and abs(sample.std() - 1.0) < 0.02


def test_fully_masked_attention_row_is_zero_not_nan():
    scores = jnp.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    mask = jnp.array([[1.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    weights = graph.float_mask_attention_weights(scores, mask)
    np.testing.assert_allclose(weights[1], 0.0)
    np.testing.assert_allclose(weights[0].sum(), 1.0, rtol=1e-6)
    assert weights[0, 1] == 0.0
    grads = jax.grad(lambda s: graph.float_mask_attention_weights(s, mask)[..., 0].sum())(scores)
    assert np.all(np.isfinite(grads))


@pytest.mark.parametrize("num_edge_heads", [1, 2, 4, 8, 16])
def test_head_totals_sum_each_heads_groups_along_any_axis(num_edge_heads):
    # Each group gets the total of the G/n consecutive groups of its head, which is what the
    # (G, G) group-to-head matrix does when contracted in and back out.
    per_group = jax.random.normal(jax.random.key(num_edge_heads), (3, 16, 5))
    heads = group_to_head(16, jnp.asarray(num_edge_heads))
    expected = jnp.einsum("agb,gh,kh->akb", per_group, heads, heads)
    totals = jax.jit(head_totals, static_argnums=2)(per_group, jnp.asarray(num_edge_heads), 1)
    np.testing.assert_allclose(totals, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(head_totals(per_group, jnp.asarray(num_edge_heads), -2), totals)


# --- the whole model -----------------------------------------------------------------------

def test_padding_leaves_real_pedestrians_unchanged(params, walk):
    positions, mask = walk
    noise = random_noise(jax.random.key(5), 1, N)
    small = run(params, scene_batch(positions, mask), noise)
    order = np.arange(N)
    padded = run(params, move_batch(positions, mask, N + 3, order), move_noise(noise, N + 3, order))
    np.testing.assert_allclose(padded.displacements[:, :, :N], small.displacements, atol=1e-5)
    np.testing.assert_allclose(padded.edge_probs[..., :N, :, :N], small.edge_probs[..., :N],
                               atol=1e-5)
    np.testing.assert_allclose(padded.edge_probs[..., :N, :, -1], small.edge_probs[..., -1],
                               atol=1e-5)
    np.testing.assert_array_equal(padded.displacements[:, :, N:], 0.0)


def test_permuting_pedestrians_permutes_outputs(params, walk):
    positions, mask = walk
    noise = random_noise(jax.random.key(6), 1, N)
    base = run(params, scene_batch(positions, mask), noise)
    order = np.array([3, 0, 4, 1, 2])        # pedestrian k moves to slot order[k]
    moved = run(params, move_batch(positions, mask, N, order), move_noise(noise, N, order))
    np.testing.assert_allclose(moved.displacements[:, :, order], base.displacements, atol=1e-5)
    columns = np.append(order, N)
    np.testing.assert_allclose(moved.sampled_edges[:, :, order][..., columns],
                               base.sampled_edges, atol=1e-5)


def test_absent_pedestrian_gives_no_nan_in_outputs_or_gradients(params, walk):
    positions, mask = walk
    mask = mask.copy()
    mask[:, :, 2] = 0                        # never detected
    mask[:, 7, 1] = 0                        # missing at the last observed step: not predicted
    batch = scene_batch(positions, mask)
    noise = random_noise(jax.random.key(7), 1, N)
    output = run(params, batch, noise, hard=False)
    for leaf in jax.tree.leaves(output):
        assert np.all(np.isfinite(leaf))
    np.testing.assert_array_equal(output.predicted_mask[0], [1, 0, 0, 1, 1])
    np.testing.assert_array_equal(output.displacements[0, :, 1:3], 0.0)
    for output_type in ("deterministic", "gaussian"):
        config = dataclasses.replace(CONFIG, output=output_type)
        grads = jax.jit(jax.grad(lambda p: batch_loss(
            config, run(p, batch, noise, hard=False, config=config), batch)))(params)
        for leaf in jax.tree.leaves(grads):
            assert np.all(np.isfinite(leaf))


def test_hard_samples_pick_exactly_n_neighbours(params, walk):
    positions, mask = walk
    output = run(params, scene_batch(positions, mask), random_noise(jax.random.key(8), 1, N))
    sampled = np.asarray(output.sampled_edges)            # (B, S, N, G, L)
    assert set(np.unique(sampled)) <= {0.0, 1.0}
    valid_targets = np.asarray(output.edge_probs).sum(axis=(-2, -1)) > 0
    np.testing.assert_array_equal(sampled.sum(axis=(-2, -1))[valid_targets], CONFIG.num_edge_heads)
    assert np.all(sampled[..., CONFIG.num_edge_heads:, :] == 0)   # inactive head slots


def test_same_key_same_output_different_key_different_edges(params, walk):
    positions, mask = walk
    batch = scene_batch(positions, mask)
    controls = Controls.make(0.5, 4, True)
    go = jax.jit(lambda key: rollout(params, key, batch, CONFIG, controls, hard=True,
                                     deterministic=True))
    a, b, c = go(jax.random.key(1)), go(jax.random.key(1)), go(jax.random.key(2))
    np.testing.assert_array_equal(a.displacements, b.displacements)
    np.testing.assert_array_equal(a.sampled_edges, b.sampled_edges)
    assert not np.array_equal(a.sampled_edges, c.sampled_edges)


def test_traced_n_matches_a_program_built_for_that_n(params, walk):
    """One program (16 head slots) vmapped over n equals programs with exactly n slots."""
    positions, mask = walk
    batch = scene_batch(positions, mask)
    noise = random_noise(jax.random.key(9), 1, N)
    heads = jnp.array([0, 1, 2, 4])

    def one(n):
        controls = Controls(tau=jnp.float32(0.5), num_edge_heads=n, ghost=jnp.bool_(True))
        return rollout_with_noise(params, noise, batch, CONFIG, controls, hard=False).displacements

    swept = jax.jit(jax.vmap(one))(heads)
    for k, n in enumerate([0, 1, 2, 4]):
        exact = dataclasses.replace(CONFIG, num_edge_heads=n, max_edge_heads=0)  # max(n, 1) slots
        small_noise = dataclasses.replace(
            noise, gumbel_obs=noise.gumbel_obs[..., :exact.head_slots, :],
            gumbel_pred=noise.gumbel_pred[..., :exact.head_slots, :])
        alone = run(params, batch, small_noise, hard=False, config=exact)
        np.testing.assert_allclose(swept[k], alone.displacements, atol=2e-5, err_msg=f"n={n}")
    assert not np.allclose(swept[1], swept[3])


def test_tcn_readout_predicts_from_observations_only_without_nan(walk):
    """The release's TCN variant: S = T_obs selector calls, future positions ignored,
    absent pedestrians give finite outputs and gradients (D and P)."""
    positions, mask = walk
    mask = mask.copy()
    mask[:, :, 2] = 0
    for output_type in ("deterministic", "gaussian"):
        config = dataclasses.replace(CONFIG, temporal="tcn", output=output_type)
        params = INIT(config, jax.random.key(0))
        noise = random_noise(jax.random.key(9), 1, N, config)
        batch = scene_batch(positions, mask)
        output = run(params, batch, noise, hard=False, config=config)
        assert output.displacements.shape == (1, config.pred_len, N, 2)
        assert output.sampled_edges.shape[1] == config.obs_len
        np.testing.assert_array_equal(output.displacements[0, :, 2], 0.0)
        future_moved = positions.copy()
        future_moved[:, config.obs_len:] += 5.0
        moved = run(params, scene_batch(future_moved, mask), noise, hard=False, config=config)
        np.testing.assert_array_equal(moved.displacements, output.displacements)
        grads = jax.jit(jax.grad(lambda p: batch_loss(
            config, run(p, batch, noise, hard=False, config=config), batch)))(params)
        assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(grads))
        assert np.abs(grads["tcn"]["time_conv_0"]["kernel"]).sum() > 0


def test_hash_dropout_is_bernoulli_with_independent_masks_per_key():
    dropout = Dropout(0.1)
    x = jnp.ones((64, 50, 128))
    apply = jax.jit(lambda key: dropout.apply({}, x, deterministic=False, rngs={"dropout": key}))
    first, second = np.asarray(apply(jax.random.key(0))), np.asarray(apply(jax.random.key(1)))
    kept, kept_too = first > 0, second > 0
    assert abs(kept.mean() - 0.9) < 3e-3                     # 409600 draws: sd 5e-4
    np.testing.assert_allclose(first[kept], 1 / 0.9, rtol=1e-6)
    assert abs((kept == kept_too).mean() - 0.82) < 3e-3      # independent: 0.9^2 + 0.1^2
    for stripe in (kept[:, :, 0], kept[:, 0, :], kept[0]):  # no stripe along any axis
        assert abs(stripe.mean() - 0.9) < 4 * np.sqrt(0.09 / stripe.size)
    assert dropout.apply({}, x, deterministic=True) is x


def test_encoder_attention_weights_are_dropped_in_training_as_the_release_does():
    """The release's node encoder calls torch's multi-head attention with dropout 0.1, which
    drops attention weights (after the graph mask) as well as the layer's outputs."""
    from gst_jax.model.encoder import NodeEncoderLayer

    layer, n = NodeEncoderLayer(ModelConfig()), 40
    x = jax.random.normal(jax.random.key(0), (8, n, 32))
    valid = jnp.ones((8, n))
    adjacency = jnp.ones((8, n, n + 1))                     # everyone attends to everyone
    variables = layer.init(jax.random.key(1), x, valid, adjacency, True, deterministic=True)
    (_, weights), captured = layer.apply(
        variables, x, valid, adjacency, True, deterministic=False,
        rngs={"dropout": jax.random.key(2)}, capture_intermediates=True)
    kept = np.asarray(captured["intermediates"]["attention_dropout"]["__call__"][0])
    ratio = kept / np.asarray(weights)                      # (8, heads, n, n + 1), all > 0
    np.testing.assert_allclose(np.unique(np.round(ratio, 5)), [0.0, 1 / 0.9], rtol=1e-5)
    assert abs((ratio > 0).mean() - 0.9) < 0.01             # 105k draws: sd 1e-3
    _, evaluated = layer.apply(variables, x, valid, adjacency, True, deterministic=True)
    np.testing.assert_array_equal(evaluated, weights)       # returned before dropout


def test_draws_of_a_window_do_not_depend_on_its_padding():
    """Gumbel noise and dropout masks of the real pedestrians and of the ghost are the same
    for a window padded to 5 or to 9 slots (what size-packed training steps rely on)."""
    key = jax.random.key(3)
    small, large = (sample_gumbel(key, (8, n, 2, n + 1)) for n in (5, 9))
    np.testing.assert_array_equal(small[:, :, :, :5], large[:, :5, :, :5])
    np.testing.assert_array_equal(small[..., -1], large[:, :5, :, -1])            # the ghost
    dropout = Dropout(0.5, ghost_axis=-2)
    masks = [np.asarray(dropout.apply({}, jnp.ones((8, n, n + 1, 16)), deterministic=False,
                                      rngs={"dropout": key})) for n in (5, 9)]
    np.testing.assert_array_equal(masks[0][:, :, :5], masks[1][:, :5, :5])
    np.testing.assert_array_equal(masks[0][:, :, -1], masks[1][:, :5, -1])
    assert 0.4 < (masks[0] > 0).mean() < 0.6


def test_gst_p_loss_scores_the_partially_detected_only_with_score_partial():
    """Unit Gaussians (mu 0, sigma 1, rho 0): a step's NLL is |d|^2 / 2. Pedestrian 0 is fully
    detected (NLL 0.5 and 2.0: mean 1.25); pedestrian 1 is predicted but not fully detected,
    its future known at step 1 only (NLL 2.0; step 2's displacement is not its own);
    pedestrian 2 is not predicted. The release scores pedestrian 0 alone: 1.25; with
    score_partial both: (1.25 + 2.0) / 2."""
    from gst_jax.model.heads import Losses, head

    true = jnp.array([[[[1.0, 0.0], [2.0, 0.0], [9.0, 9.0]],
                       [[0.0, 2.0], [3.0, 3.0], [9.0, 9.0]]]])                 # (1, P=2, N=3, 2)
    zeros = jnp.zeros_like(true)
    common = dict(displacements=zeros, mu=zeros, sigma=jnp.ones_like(true),
                  corr=jnp.zeros(true.shape[:-1]), true_displacements=true,
                  step_mask=jnp.array([[[1.0, 1.0, 0.0], [1.0, 0.0, 0.0]]]),
                  fully_detected=jnp.array([[1.0, 0.0, 0.0]]))
    loss = head("gaussian").scene_loss
    np.testing.assert_allclose(loss(Losses(**common)), [1.25], rtol=1e-6)
    np.testing.assert_allclose(loss(Losses(**common, score_partial=jnp.bool_(False))), [1.25],
                               rtol=1e-6)
    np.testing.assert_allclose(loss(Losses(**common, score_partial=jnp.bool_(True))), [1.625],
                               rtol=1e-6)


def test_hidden_histories_start_late_keep_the_last_two_steps_and_only_with_a_chance():
    """augment.hide_history: with chance 1 every pedestrian is seen from a step k in 1..3 of
    5 observed on (positions zeroed before it, node mask as docs/MODEL.md 1.6 says of the new
    position mask), the last two observed steps and the future untouched; chance 0 changes
    nothing."""
    from gst_jax import augment

    batch_size, steps, people, obs_len = 4, 10, 6, 5
    positions = jnp.asarray(np.random.default_rng(0).normal(size=(batch_size, steps, people, 2)),
                            jnp.float32)
    mask = jnp.ones((batch_size, steps, people))
    batch = SceneBatch(positions=positions, position_mask=mask,
                       node_mask=node_mask_from_positions(mask), scene_mask=jnp.ones(batch_size),
                       window_index=jnp.arange(batch_size, dtype=jnp.int32))
    same = augment.hide_history(jax.random.key(0), batch, 0.0, obs_len)
    for a, b in zip(same, batch):
        np.testing.assert_array_equal(a, b)
    hidden = augment.hide_history(jax.random.key(0), batch, 1.0, obs_len)
    starts = np.argmax(np.asarray(hidden.position_mask) > 0, axis=1)             # (B, N)
    assert set(starts.ravel().tolist()) == {1, 2, 3}
    for b in range(batch_size):
        for n in range(people):
            k = starts[b, n]
            np.testing.assert_array_equal(hidden.position_mask[b, :, n],
                                          [0] * k + [1] * (steps - k))
            np.testing.assert_array_equal(hidden.positions[b, :k, n], 0)
            np.testing.assert_array_equal(hidden.positions[b, k:, n], positions[b, k:, n])
            np.testing.assert_array_equal(hidden.node_mask[b, :, n],
                                          [0] * (k + 1) + [1] * (steps - k - 1))
