"""Replaying one run of the authors' release, for the parity tests (tests/test_parity.py).

`reference_forward` / `reference_loss_and_grads` take a release run's weights, inputs, Gumbel
noise and normals, and return its outputs, loss and gradients in the release's own names and
layouts, so that they compare array for array with the parity fixture.
"""

from __future__ import annotations

import functools
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch, node_mask_from_positions
from gst_jax.interop import load_state_dict, params_from_torch, params_to_torch
from gst_jax.losses import scene_losses
from gst_jax.model import Controls
from gst_jax.model.heads import safe_ratio
from gst_jax.rollout import RolloutNoise, RolloutOutput, rollout_with_noise

MISSING = -999.0  # the release marks undetected positions with this value


def batch_loss(config: ModelConfig, output: RolloutOutput, batch: SceneBatch) -> jax.Array:
    """Mean of the per-scene losses over the real (non-padding) scenes of the batch: the
    release's loss of one batch."""
    return safe_ratio(jnp.sum(scene_losses(config, output, batch) * batch.scene_mask),
                      jnp.sum(batch.scene_mask))


def batch_from_reference_inputs(inputs: Mapping[str, np.ndarray]) -> SceneBatch:
    """One-scene SceneBatch from the release's `obs_traj`/`pred_traj` (1, N, 2, T),
    -999 = missing."""
    trajectory = np.concatenate([inputs["obs_traj"], inputs["pred_traj"]], axis=-1)[0]
    positions = np.transpose(trajectory, (2, 0, 1)).astype(np.float32)        # (T, N, 2)
    position_mask = np.all(positions != MISSING, axis=-1).astype(np.float32)
    positions = np.where(position_mask[..., None] > 0, positions, 0.0)
    return SceneBatch(positions=positions[None], position_mask=position_mask[None],
                      node_mask=node_mask_from_positions(position_mask)[None],
                      scene_mask=np.ones((1,), np.float32),
                      window_index=np.zeros((1,), np.int32))


def noise_from_reference(gumbel: Sequence[np.ndarray], normals: Sequence[np.ndarray] | None,
                         num_nodes: int, config: ModelConfig) -> RolloutNoise:
    """Pad the release's per-call noise (.., N, n, N(+1)) into the (.., N, G, N+1) layout."""
    head_slots, neighbours = config.head_slots, num_nodes + 1
    if gumbel:
        padded = [np.pad(g, [(0, 0), (0, 0), (0, head_slots - g.shape[2]),
                             (0, neighbours - g.shape[3])]) for g in gumbel]
    else:  # n = 0: no selector, no noise
        padded = [np.zeros((config.obs_len if k == 0 else 1, num_nodes, head_slots, neighbours))
                  for k in range(config.pred_len)]
    if normals is None:
        normal = np.zeros((config.pred_len, 1, num_nodes, 2), np.float32)
    else:
        normal = np.stack([np.reshape(e, (1, num_nodes, 2)) for e in normals])
    return RolloutNoise(gumbel_obs=jnp.asarray(padded[0][None], jnp.float32),
                        gumbel_pred=jnp.asarray(np.stack(padded[1:]), jnp.float32),
                        normal=jnp.asarray(normal, jnp.float32))


@functools.partial(jax.jit, static_argnames=("config", "hard", "return_attention"))
def _replay(params, batch, noise, controls, *, config, hard, return_attention):
    """Loss and outputs of one replayed run. n and ghost are traced: one compile per shape."""
    out = rollout_with_noise(params, noise, batch, config, controls, hard=hard,
                             return_attention=return_attention)
    return batch_loss(config, out, batch), out


def _replay_inputs(state_dict, inputs, gumbel, normals, *, num_edge_heads, ghost, tau, output,
                   max_edge_heads, attention="release"):
    config = ModelConfig(max_edge_heads=max_edge_heads, output=output, attention=attention)
    params = params_from_torch(load_state_dict(state_dict), num_edge_heads=num_edge_heads,
                               ghost=ghost, config=config)
    batch = batch_from_reference_inputs(inputs)
    noise = noise_from_reference(gumbel, normals, batch.shape[2], config)
    return config, params, batch, noise, Controls.make(tau, num_edge_heads, ghost)


def reference_forward(state_dict, inputs: Mapping[str, np.ndarray], gumbel: Sequence[np.ndarray],
                      *, num_edge_heads: int, ghost: bool, tau: float, hard: bool,
                      normals: Sequence[np.ndarray] | None = None,
                      output: str = "deterministic", max_edge_heads: int = 16,
                      attention: str = "release") -> dict:
    """Replay one release forward pass; outputs in the release's layouts (see the fixture).
    attention: 'masked' replays the same weights and noise with the masked softmax instead
    of the release's attention (`ModelConfig.attention`)."""
    config, params, batch, noise, controls = _replay_inputs(
        state_dict, inputs, gumbel, normals, num_edge_heads=num_edge_heads, ghost=ghost,
        tau=tau, output=output, max_edge_heads=max_edge_heads, attention=attention)
    loss, out = _replay(params, batch, noise, controls, config=config, hard=hard,
                        return_attention=True)
    heads = max(num_edge_heads, 1)
    neighbours = batch.shape[2] + 1 if ghost else batch.shape[2]
    edges = lambda a: np.asarray(a[0, :, :, :heads, :neighbours])
    return {"mu": np.asarray(out.mu), "sx": np.asarray(out.sigma[..., :1]),
            "sy": np.asarray(out.sigma[..., 1:]), "corr": np.asarray(out.corr[..., None]),
            "x_pred": np.asarray(out.displacements),
            "edge_multinomial": edges(out.edge_probs), "sampled_edges": edges(out.sampled_edges),
            "attn_weights": np.asarray(out.attention[:, 0, ..., :neighbours]),
            "loss": np.asarray(loss)}


def reference_loss_and_grads(state_dict, inputs: Mapping[str, np.ndarray],
                             gumbel: Sequence[np.ndarray], *, num_edge_heads: int, ghost: bool,
                             tau: float, hard: bool, normals: Sequence[np.ndarray] | None = None,
                             output: str = "deterministic",
                             max_edge_heads: int = 16) -> tuple[np.ndarray, dict]:
    """Loss of one replayed release run and its gradients, keyed by torch names, torch layout."""
    config, params, batch, noise, controls = _replay_inputs(
        state_dict, inputs, gumbel, normals, num_edge_heads=num_edge_heads, ghost=ghost,
        tau=tau, output=output, max_edge_heads=max_edge_heads)
    loss, grads = _replay_value_and_grad(params, batch, noise, controls, config=config, hard=hard)
    return np.asarray(loss), params_to_torch(grads, num_edge_heads=num_edge_heads, config=config)


@functools.partial(jax.jit, static_argnames=("config", "hard"))
def _replay_value_and_grad(params, batch, noise, controls, *, config, hard):
    loss_only = lambda p: _replay(p, batch, noise, controls, config=config, hard=hard,
                                  return_attention=False)[0]
    return jax.value_and_grad(loss_only)(params)
