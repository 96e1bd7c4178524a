"""The masked softmax (`ModelConfig.attention = 'masked'`): the release's attention wherever
that does not underflow, and no row lost or changed by padding where it does."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import graph
from gst_jax.testing import release

FIXTURE = Path(__file__).parent / "fixtures" / "gst_reference_parity.npz"


def test_masked_softmax_equals_the_releases_where_it_does_not_underflow():
    rng = np.random.default_rng(0)
    scores = jnp.asarray(rng.normal(0.0, 3.0, (200, 9)), jnp.float32)
    binary = jnp.asarray(rng.random((200, 9)) < 0.6, jnp.float32).at[:, 0].set(1.0)
    soft = jax.nn.softmax(jnp.asarray(rng.normal(0.0, 2.0, (200, 9)), jnp.float32)) * binary
    # The release's +1e-10 in its normaliser moves a soft row whose kept mass is ~1e-5 by
    # ~1e-5 of itself: the tolerance allows that, not more.
    for mask, tolerance in ((binary, 2e-6), (soft, 2e-5)):
        np.testing.assert_allclose(graph.masked_softmax_weights(scores, mask),
                                   graph.float_mask_attention_weights(scores, mask),
                                   atol=tolerance)


def test_masked_softmax_keeps_a_row_the_releases_underflows_and_ignores_its_padding():
    # One valid entry, then padding whose scores dominate by 40: the release's softmax gives
    # the valid entry e^-40 of the mass, which its renormalisation (+1e-10) cannot recover,
    # and how much it keeps depends on how many padded entries there are.
    def row(padding):
        scores = jnp.array([0.0] + [40.0] * padding)
        mask = jnp.array([1.0] + [0.0] * padding)
        return scores, mask

    for padding in (1, 5):
        assert graph.float_mask_attention_weights(*row(padding))[0] < 1e-3
        np.testing.assert_array_equal(graph.masked_softmax_weights(*row(padding))[0], 1.0)
    release_rows = [graph.float_mask_attention_weights(*row(p))[0] for p in (1, 5)]
    assert not np.isclose(*release_rows, rtol=1e-3)


def test_masked_softmax_gives_zero_rows_and_finite_gradients_for_any_mask():
    rng = np.random.default_rng(1)
    # Masks down to 1e-45 (denormal) and scores far apart: a softmax of s + log m, whose
    # largest entry is exp(0), cannot underflow however small the mask; no kept entry: zeros.
    scores = jnp.asarray(rng.normal(0.0, 100.0, (500, 5)), jnp.float32)
    mask = np.where(rng.random((500, 5)) < 0.3, 0.0, 10.0 ** rng.uniform(-45, 0, (500, 5)))
    mask[:10] = 0.0
    mask = jnp.asarray(mask, jnp.float32)
    weights = graph.masked_softmax_weights(scores, mask)
    kept_any = np.asarray(mask > 0).any(-1)
    np.testing.assert_allclose(weights.sum(-1)[kept_any], 1.0, rtol=1e-5)
    np.testing.assert_array_equal(weights[~kept_any], 0.0)
    assert not np.asarray(weights)[np.asarray(mask) == 0].any()
    grads = jax.grad(lambda s, m: (graph.masked_softmax_weights(s, m) * jnp.arange(5.0)).sum(),
                     argnums=(0, 1))(scores, mask)
    assert all(np.isfinite(g).all() for g in grads)


@pytest.mark.parametrize("run", ["eval_hard", "train_soft"])
def test_masked_attention_replays_the_release_where_it_does_not_underflow(run):
    # The release's recorded weights, inputs and noise (n = 4, ghost, ETH), replayed with the
    # masked softmax in the selector, the encoder and the edge probabilities.
    with np.load(FIXTURE) as f:
        fixture = {name: f[name] for name in f.files}
    prefix = f"n4_ghost/eth_test_20/{run}/"
    recorded = {k[len(prefix):]: v for k, v in fixture.items() if k.startswith(prefix)}
    weights = {k[len("n4_ghost/weights/"):]: v for k, v in fixture.items()
               if k.startswith("n4_ghost/weights/")}
    inputs = {k[len("n4_ghost/eth_test_20/input/"):]: v for k, v in fixture.items()
              if k.startswith("n4_ghost/eth_test_20/input/")}
    gumbel = [recorded[f"gumbel/{k:02d}"] for k in range(12)]
    ours = release.reference_forward(weights, inputs, gumbel, num_edge_heads=4, ghost=True,
                                     tau=float(recorded["tau"]), hard="hard" in run,
                                     attention="masked")
    compared = [name for name in ("mu", "x_pred", "edge_multinomial", "sampled_edges",
                                  "attn_weights") if name in recorded]
    assert {"mu", "x_pred", "edge_multinomial", "sampled_edges"} <= set(compared)
    for name in compared:
        np.testing.assert_allclose(ours[name], recorded[name], rtol=0, atol=1e-4, err_msg=name)
