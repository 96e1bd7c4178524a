"""Jitted prediction: K samples of every pedestrian's next 12 positions.

    predict = make_predict(config, num_samples=20)
    prediction = predict(params, key, batch)        # compiled once per batch shape

Samples are a `vmap` over split keys; the observed steps' edge probabilities, which do not
depend on the sample, are computed once. Evaluation protocol (docs/MODEL.md 4): hard Gumbel
samples at tau = 0.03, no dropout; GST (P) also samples its Gaussian.
"""

from __future__ import annotations

from typing import Any, Callable

import flax
import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.model import Controls
from gst_jax.rollout import observed_edge_probabilities, rollout


@flax.struct.dataclass
class Prediction:
    """K sampled futures of B scenes. S = obs_len + pred_len - 1 selector calls.

    positions: (K, B, P, N, 2) positions (the frame of the observations); NaN for pedestrians
      not predicted, so that nobody mistakes them for predictions.
    displacements: (K, B, P, N, 2) per-step displacements.
    mu, sigma: (K, B, P, N, 2); corr: (K, B, P, N) Gaussian parameters (GST (P) samples them).
    sampled_adjacency: (K, B, S, N, N+1) sampled neighbours per target (ghost last), or None.
    edge_probs: (K, B, S, N, G, N+1) edge probabilities per head slot, or None.
    predicted_mask: (B, N) 1 for the pedestrians predicted: those detected at both of the
      last two observed steps (their last displacement exists; docs/MODEL.md 2.3).
    """

    positions: jax.Array
    displacements: jax.Array
    mu: jax.Array
    sigma: jax.Array
    corr: jax.Array
    sampled_adjacency: Any
    edge_probs: Any
    predicted_mask: jax.Array


def make_predict(config: ModelConfig, num_samples: int = 20, *, with_graph: bool = True,
                 mean: bool = False) -> Callable[..., Prediction]:
    """Build the jitted `predict(params, key, batch, controls=None) -> Prediction`.

    `controls` overrides the traced switches (n, ghost, tau); by default the config's n and
    ghost with tau = 0.03. `with_graph=False` drops the per-step graphs (they dominate memory
    for large K and N) when only trajectories are needed. `mean=True` predicts every step as
    the mean of the head's Gaussian (GST (P) without sampling its displacements). A batch
    holds T = obs_len observed steps (`make_batch`), or obs_len + pred_len (windows with
    their future, evaluation).
    """
    if num_samples < 1:
        raise ValueError(f"num_samples must be at least 1, got {num_samples}")
    steps = (config.obs_len, config.obs_len + config.pred_len)

    @jax.jit
    def predict(params, key: jax.Array, batch: SceneBatch,
                controls: Controls | None = None) -> Prediction:
        if batch.positions.shape[1] not in steps:
            raise ValueError(f"the batch has {batch.positions.shape[1]} steps; expected "
                             f"{steps[0]} observed steps (or {steps[1]} with the future)")
        if controls is None:
            controls = Controls.from_config(config)

        # The observed steps' edge probabilities do not depend on the sample: computed once.
        observed_probs = (observed_edge_probabilities(params, batch, config, controls)
                          if config.selects_edges else None)

        def one_sample(sample_key):
            out = rollout(params, sample_key, batch, config, controls, hard=True,
                          deterministic=True, observed_edge_probs=observed_probs, mean=mean)
            graph = (out.sampled_edges.sum(axis=-2), out.edge_probs) if with_graph else (None, None)
            return out.displacements, out.mu, out.sigma, out.corr, graph

        displacements, mu, sigma, corr, (adjacency, probs) = jax.vmap(one_sample)(
            jax.random.split(key, num_samples))
        keep = batch.predicted_mask(config.obs_len)
        last_position = batch.positions[:, config.obs_len - 1] * keep[..., None]
        positions = jnp.where(keep[:, None, :, None] > 0,
                              last_position[:, None] + jnp.cumsum(displacements, axis=2), jnp.nan)
        return Prediction(positions=positions, displacements=displacements, mu=mu, sigma=sigma,
                          corr=corr, sampled_adjacency=adjacency, edge_probs=probs,
                          predicted_mask=keep)

    return predict
