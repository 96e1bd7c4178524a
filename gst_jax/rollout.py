"""The recurrent rollout (docs/MODEL.md 2.3): observe 8 steps at once, then scan 12 predictions.

Observation: the selector and encoder run on all observed steps in one call, and the masked
LSTM folds them with `lax.scan`. Prediction: a `lax.scan` over the remaining steps whose
carry holds the LSTM state, the last displacement, the evolving edges and the PRNG key; it
runs on the first P slots when the batch says the pedestrians to predict sit there
(`SceneBatch.predicted_slots`), since nobody else takes part after the observation.
With `temporal='tcn'` the prediction is instead the release's convolutional readout of the
encoded observed steps, all predicted steps at once. With `mean=True` every predicted step is
the mean of the output head's Gaussian (CrowdNav++'s `sampling=False`), whatever the head.

Noise comes either from a key (`rollout`) or from recorded arrays (`rollout_with_noise`, used
to replay the release's Gumbel and normal draws in the parity tests); both share one body.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import flax
import jax
import jax.numpy as jnp

from gst_jax import graph, noise
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.gumbel import sample_gumbel
from gst_jax.model import GST, Controls, Params, heads

__all__ = ["Controls", "RolloutNoise", "RolloutOutput", "observed_edge_probabilities", "rollout",
           "rollout_with_noise"]


@flax.struct.dataclass
class RolloutNoise:
    """Every random draw of one rollout, L = N + 1 neighbours (ghost last), G head slots.

    gumbel_obs: (B, T_obs, N, G, L) noise of the observation call.
    gumbel_pred: (P - 1, B, N, G, L) noise of the prediction calls, in order.
    normal: (P, B, N, 2) standard normals of GST (P)'s sampled displacements.
    """

    gumbel_obs: jax.Array
    gumbel_pred: jax.Array
    normal: jax.Array


@flax.struct.dataclass
class RolloutOutput:
    """What one rollout produced. S selector calls, observation first: T_obs + P - 1 with the
    LSTM, T_obs with the TCN readout (which does not interact while predicting).

    displacements: (B, P, N, 2) predicted displacements, zero for pedestrians not predicted
      (GST (D): mu; GST (P): the sampled displacement).
    mu, sigma: (B, P, N, 2); corr: (B, P, N): Gaussian parameters from the output head.
    edge_probs, sampled_edges: (B, S, N, G, L) per target, head slot and neighbour (in the
      prediction steps, zero for targets beyond the predicted slots).
    predicted_mask: (B, N) keep: pedestrians valid at the last observed step.
    attention: (layers, B, S, heads, N, L) encoder attention, or None unless requested.
    """

    displacements: jax.Array
    mu: jax.Array
    sigma: jax.Array
    corr: jax.Array
    edge_probs: jax.Array
    sampled_edges: jax.Array
    predicted_mask: jax.Array
    attention: jax.Array | None = None


def rollout(params: Params, key: jax.Array, batch: SceneBatch, config: ModelConfig,
            controls: Controls, *, hard: bool, deterministic: bool, return_attention: bool = False,
            observed_edge_probs: jax.Array | None = None, mean: bool = False) -> RolloutOutput:
    """Predict `config.pred_len` steps for every pedestrian of `batch`, drawing noise from `key`.

    `observed_edge_probs` (from `observed_edge_probabilities`, deterministic rollouts only)
    skips the observation pass's edge selector, so that samples share it. mean: every step
    is the head's mean, not its draw.
    """
    return _rollout(params, key, None, batch, config, controls, hard=hard,
                    deterministic=deterministic, return_attention=return_attention,
                    observed_edge_probs=observed_edge_probs, mean=mean)


def observed_edge_probabilities(params: Params, batch: SceneBatch, config: ModelConfig,
                                controls: Controls, *, steps_at_once: int | None = None
                                ) -> jax.Array:
    """Edge probabilities of the observed steps without dropout, (B, T_obs, N, G, N+1).

    They depend on the observations only, not on the noise: K samples of one batch need them
    once (8 of the 19 selector calls of a rollout). steps_at_once: select that many observed
    steps per call, in a loop (None: all at once); the selector's per-target attention is
    (N, N+1, N+1) a step, so for large crowds this bounds memory.
    """
    def select(inputs):
        return GST(config).apply({"params": params}, *inputs, controls, deterministic=True,
                                 method=GST.select)

    def one_window(window):
        inputs = _observed_inputs(window, config.obs_len)
        return (select(inputs) if steps_at_once is None
                else jax.lax.map(select, inputs, batch_size=steps_at_once))

    return jax.vmap(one_window)(batch)


def _observed_inputs(window: SceneBatch, obs_len: int):
    """Node features (T, N, 2), edge features (T, N, N, 2) and node mask (T, N) of the
    observed steps of one window."""
    node_mask = window.node_mask[:obs_len]
    positions = window.positions[:obs_len]
    return (graph.displacements(positions, node_mask), graph.edge_features(positions, node_mask),
            node_mask)


def rollout_with_noise(params: Params, noise: RolloutNoise, batch: SceneBatch, config: ModelConfig,
                       controls: Controls, *, hard: bool, deterministic: bool = True,
                       dropout_key: jax.Array | None = None,
                       return_attention: bool = False) -> RolloutOutput:
    """Like `rollout`, but replaying recorded noise (dropout, if on, still uses a key)."""
    key = jax.random.key(0) if dropout_key is None else dropout_key
    return _rollout(params, key, noise, batch, config, controls, hard=hard,
                    deterministic=deterministic, return_attention=return_attention)


class RolloutKeys(NamedTuple):
    """The keys of one window's rollout, split once by purpose."""

    gumbel_obs: jax.Array     # Gumbel noise of the observation call
    dropout_obs: jax.Array    # dropout of the observation call
    normal: jax.Array         # GST (P)'s standard normals, all predicted steps
    steps: jax.Array          # the prediction steps' keys (split once more per step)

    @classmethod
    def split(cls, key: jax.Array) -> "RolloutKeys":
        rest, gumbel_obs, dropout_obs = jax.random.split(key, 3)
        steps, normal = jax.random.split(rest)
        return cls(gumbel_obs, dropout_obs, normal, steps)


class PredictionCarry(NamedTuple):
    """What one prediction step hands to the next, for one window of N pedestrians."""

    hidden: jax.Array         # (N, H) LSTM state
    cell: jax.Array           # (N, H)
    delta: jax.Array          # (N, 2) the last predicted displacement
    edges: jax.Array          # (N, N, 2) relative positions A[j, i], evolved by the deltas
    key: jax.Array


# vmap's axes: the trees of the outputs and of the noise with each field's window axis in
# place of its array (so the ignores: ints where the fields are typed arrays).
# Where the window axis of each output sits (attention is (layers, B, S, heads, N, L)).
_OUTPUT_AXES = RolloutOutput(displacements=0, mu=0, sigma=0, corr=0, edge_probs=0,  # type: ignore[arg-type]
                             sampled_edges=0, predicted_mask=0, attention=1)  # type: ignore[arg-type]
# The window axis of recorded noise (gumbel_pred and normal are step-major).
_NOISE_AXES = RolloutNoise(gumbel_obs=0, gumbel_pred=1, normal=1)  # type: ignore[arg-type]


def _rollout(params: Params, key: jax.Array, recorded: RolloutNoise | None, batch: SceneBatch,
             config: ModelConfig, controls: Controls, *, hard: bool, deterministic: bool,
             return_attention: bool, observed_edge_probs: jax.Array | None = None,
             mean: bool = False) -> RolloutOutput:
    """The rollout of every window of `batch`: `_rollout_window` vmapped over windows, each
    with its own key (`noise.window_keys`), so that a window's draws do not depend on the
    other windows of its batch."""
    def one_window(key, recorded, window, observed_edge_probs):
        return _rollout_window(params, key, recorded, window, config, controls, hard=hard,
                               deterministic=deterministic, return_attention=return_attention,
                               observed_edge_probs=observed_edge_probs, mean=mean)

    in_axes = (0, None if recorded is None else _NOISE_AXES, 0,
               None if observed_edge_probs is None else 0)
    out_axes = (_OUTPUT_AXES if return_attention
                else dataclasses.replace(_OUTPUT_AXES, attention=None))
    return jax.vmap(one_window, in_axes=in_axes, out_axes=out_axes)(
        noise.window_keys(key, batch.window_index), recorded, batch, observed_edge_probs)


def _rollout_window(params: Params, key: jax.Array, recorded: RolloutNoise | None,
                    window: SceneBatch, config: ModelConfig, controls: Controls, *, hard: bool,
                    deterministic: bool,
                    return_attention: bool, observed_edge_probs: jax.Array | None,
                    mean: bool) -> RolloutOutput:
    """One window (the SceneBatch fields without their batch axis: positions (T, N, 2), ...)."""
    model = GST(config)
    obs_len, pred_len = config.obs_len, config.pred_len
    num_nodes = window.node_mask.shape[-1]
    noise_shape = (num_nodes, config.head_slots, num_nodes + 1)
    head = heads.head(config.output)
    keys = RolloutKeys.split(key)

    def apply(method, *args, key=None, **kwargs):
        rngs = None if deterministic or key is None else {"dropout": key}
        return model.apply({"params": params}, *args, method=method, rngs=rngs, **kwargs)

    def draw(mu, sigma, corr, normal, keep):
        return (mu if mean else head.draw(mu, sigma, corr, normal)) * keep[..., None]

    def gumbel_noise(key, shape):
        # A program without a selector (full connection alone) samples no graph.
        return sample_gumbel(key, shape) if config.selects_edges else None

    # --- Observation: one selector/encoder call over all observed steps.
    node_features, edge_features, node_mask = _observed_inputs(window, obs_len)
    if recorded is None:
        gumbel_obs = gumbel_noise(keys.gumbel_obs, (obs_len,) + noise_shape)
        normal_shape = (pred_len, num_nodes, 2)
        normal = (noise.normal(keys.normal, normal_shape) if head.sampled and not mean
                  else jnp.zeros(normal_shape))
    else:
        gumbel_obs, normal = recorded.gumbel_obs, recorded.normal
    encoded, obs_probs, obs_sampled, obs_attention = apply(
        GST.interact, node_features, edge_features, node_mask, gumbel_obs, controls,
        hard=hard, deterministic=deterministic, key=keys.dropout_obs,
        edge_probs=observed_edge_probs)
    keep = window.predicted_mask(obs_len)                                     # (N,)

    if not config.recurrent:
        # Readout: every predicted step from the observed encodings; no further interaction.
        _, dropout_key = jax.random.split(keys.steps)
        observed = encoded * node_mask[..., None] * keep[:, None]
        mu, sigma, corr = apply(GST.convolve, observed, deterministic=deterministic,
                                key=dropout_key)
        return RolloutOutput(displacements=draw(mu, sigma, corr, normal, keep), mu=mu,
                             sigma=sigma, corr=corr, edge_probs=obs_probs,
                             sampled_edges=obs_sampled, predicted_mask=keep,
                             attention=obs_attention if return_attention else None)

    def observe(state, step_inputs):
        inputs, mask = step_inputs
        return apply(GST.recur, inputs, state, mask, hold=config.temporal == "lstm"), None

    zeros = jnp.zeros((num_nodes, config.lstm_hidden), encoded.dtype)
    (hidden, cell), _ = jax.lax.scan(observe, (zeros, zeros), (encoded, node_mask))

    # --- Prediction, on the first P slots, where the pedestrians to predict sit
    # (SceneBatch.predicted_slots); coordinate-hashed noise makes their draws those of all N.
    slots = num_nodes if window.predicted_slots is None else window.predicted_slots.shape[-1]
    keep = keep[:slots]
    hidden, cell = hidden[:slots] * keep[..., None], cell[:slots] * keep[..., None]
    normal = normal[:, :slots]
    gumbel_pred = None if recorded is None else _first_slots(recorded.gumbel_pred, slots)
    # The first displacement comes straight from the observed state.
    mu, sigma, corr = apply(GST.readout, hidden)
    delta = draw(mu, sigma, corr, normal[0], keep)
    noise_shape = (slots, config.head_slots, slots + 1)

    def predict_step(carry: PredictionCarry, recorded_step):
        key, gumbel_key, dropout_key = jax.random.split(carry.key, 3)
        gumbel, normal = recorded_step
        if gumbel is None:
            gumbel = gumbel_noise(gumbel_key, noise_shape)
        # Sampled displacements feed back detached (the release's `detach_sample`).
        fed_back = jax.lax.stop_gradient(carry.delta) if head.sampled else carry.delta
        edges = carry.edges + fed_back[:, None, :] - fed_back[None, :, :]
        encoded, probs, sampled, attention = apply(
            GST.interact, fed_back, edges, keep, gumbel, controls, hard=hard,
            deterministic=deterministic, key=dropout_key)
        hidden, cell = apply(GST.recur, encoded * keep[..., None], (carry.hidden, carry.cell),
                             keep)
        mu, sigma, corr = apply(GST.readout, hidden)
        delta = draw(mu, sigma, corr, normal, keep)
        outputs = (delta, mu, sigma, corr, probs, sampled,
                   attention if return_attention else None)
        return PredictionCarry(hidden, cell, delta, edges, key), outputs

    # Rematerialised in the backward pass: storing each step's selector activations,
    # (N, L, 128) per step, costs more memory traffic than recomputing them (eth training
    # step 9.0 -> 7.8 s per epoch on the 2-core CPU; docs/benchmarks.md).
    predict_step = jax.checkpoint(predict_step)
    carry = PredictionCarry(hidden, cell, delta, edge_features[-1, :slots, :slots], keys.steps)
    _, (deltas, mus, sigmas, corrs, probs, sampled, attention) = jax.lax.scan(
        predict_step, carry, (gumbel_pred, normal[1:]), length=pred_len - 1)

    def all_slots(first, rest, fill=0.0):  # (P, ...), (P-1, P, ...) -> (P, N, ...)
        steps = jnp.concatenate([first[None], rest], axis=0)
        pad = [(0, 0), (0, num_nodes - slots)] + [(0, 0)] * (steps.ndim - 2)
        return jnp.pad(steps, pad, constant_values=fill)

    return RolloutOutput(
        displacements=all_slots(delta, deltas),
        mu=all_slots(mu, mus),
        sigma=all_slots(sigma, sigmas, fill=1.0),      # a finite NLL, masked by the losses
        corr=all_slots(corr, corrs),
        edge_probs=jnp.concatenate([obs_probs, _all_neighbours(probs, num_nodes, axis=1)]),
        sampled_edges=jnp.concatenate([obs_sampled, _all_neighbours(sampled, num_nodes, axis=1)]),
        predicted_mask=jnp.pad(keep, (0, num_nodes - slots)),
        # (layers, T_obs, heads, N, L) and (P-1, layers, heads, N, L) -> (layers, S, ...)
        attention=(jnp.concatenate([obs_attention, jnp.moveaxis(
            _all_neighbours(attention, num_nodes, axis=3), 0, 1)], axis=1)
            if return_attention else None),
    )


def _first_slots(edge_noise: jax.Array, slots: int) -> jax.Array:
    """(..., N, G, N+1) noise of all slots -> (..., P, G, P+1): the first P targets and
    neighbours, and the ghost."""
    targets = edge_noise[..., :slots, :, :]
    return jnp.concatenate([targets[..., :slots], targets[..., -1:]], axis=-1)


def _all_neighbours(per_edge: jax.Array, num_nodes: int, axis: int) -> jax.Array:
    """(..., P, ..., P+1) with targets at `axis` and neighbours (ghost last) on the last axis
    -> (..., N, ..., N+1), zero for the slots beyond P."""
    slots = per_edge.shape[axis]
    pad = [(0, 0)] * per_edge.ndim
    pad[axis] = (0, num_nodes - slots)
    per_edge = jnp.pad(per_edge, pad)
    return jnp.concatenate([per_edge[..., :slots], jnp.zeros(
        per_edge.shape[:-1] + (num_nodes - slots,), per_edge.dtype), per_edge[..., -1:]], axis=-1)
