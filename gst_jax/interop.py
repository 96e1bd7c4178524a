"""Interoperability with the authors' PyTorch release.

- `params_from_torch`: a release state dict (torch names -> arrays, or a `.pt` file when
  torch is installed) -> gst_jax parameters in the traced-n layout.
- `reference_forward` / `reference_loss_and_grads`: replay one release run (its inputs,
  Gumbel noise and normals) and return the outputs, loss and gradients in the release's own
  names and layouts, so that they compare array for array with the parity fixture.

torch is not a dependency; `.pt` files need it, plain mappings of numpy arrays do not.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax import losses
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.data.batch import node_mask_from_positions
from gst_jax.model import Controls
from gst_jax.rollout import RolloutNoise, rollout_with_noise

SELECTOR = "gumbel_social_transformer.edge_selector."
ENCODER = "gumbel_social_transformer.node_encoder_layers.{}."
MISSING = -999.0  # the release marks undetected positions with this value


def load_state_dict(source: str | Path | Mapping[str, Any]) -> dict[str, np.ndarray]:
    """A mapping of torch names to arrays, from a mapping or a `.pt` file (needs torch)."""
    if isinstance(source, Mapping):
        return {name: np.asarray(value) for name, value in source.items()}
    try:
        import torch
    except ImportError as error:
        raise ImportError(f"reading {source} needs torch; pass a dict of numpy arrays "
                          "instead (e.g. {k: v.numpy() for k, v in state_dict.items()})") from error
    # The release's checkpoints also hold its epoch metrics as numpy scalars; allow those
    # (and nothing else beyond tensors) rather than unpickling arbitrary objects.
    multiarray = (np._core if hasattr(np, "_core") else np.core).multiarray  # numpy 2 / 1
    numpy_scalars = [multiarray.scalar, np.dtype, type(np.dtype(np.float32)),
                     type(np.dtype(np.float64))]
    with torch.serialization.safe_globals(numpy_scalars):
        loaded = torch.load(str(source), map_location="cpu", weights_only=True)
    if "model_state_dict" in loaded:  # the release's checkpoint layout
        loaded = loaded["model_state_dict"]
    return {name: value.detach().cpu().numpy() for name, value in loaded.items()}


def params_from_torch(state_dict, *, num_edge_heads: int, ghost: bool,
                      max_edge_heads: int = 16, config: ModelConfig | None = None):
    """Convert release weights into gst_jax parameters (traceable, so grads flow back).

    PyTorch Linear stores W as (out, in); flax kernels are (in, out). The selector's per-head
    MLP (head_dim = 128 / n) goes into the top-left block of the padded 128 x 128 weight.
    With n = 0 the release has no selector; its parameters are zero (and unused).
    """
    state_dict = state_dict if isinstance(state_dict, Mapping) else load_state_dict(state_dict)
    if num_edge_heads and max_edge_heads % num_edge_heads:
        raise ValueError(f"num_edge_heads {num_edge_heads} must divide max_edge_heads "
                         f"{max_edge_heads}")
    config = config or ModelConfig(num_edge_heads=num_edge_heads, ghost=ghost,
                                   max_edge_heads=max_edge_heads)
    w = lambda name: jnp.asarray(state_dict[name])
    dense = lambda prefix: {"kernel": w(prefix + "weight").T, "bias": w(prefix + "bias")}
    norm = lambda prefix: {"scale": w(prefix + "weight"), "bias": w(prefix + "bias")}

    params = {"node_embedding": dense("node_embedding."),
              "edge_embedding": dense("edge_embedding."),
              "hidden2pos": dense("hidden2pos."),
              "lstm": {"weight_ih": w("lstm.weight_ih_l0").T, "weight_hh": w("lstm.weight_hh_l0").T,
                       "bias_ih": w("lstm.bias_ih_l0"), "bias_hh": w("lstm.bias_hh_l0")}}
    for layer in range(config.encoder_layers):
        prefix = ENCODER.format(layer)
        params[f"node_encoder_layers_{layer}"] = {
            "in_proj": {"kernel": w(prefix + "self_attn.in_proj_weight").T,
                        "bias": w(prefix + "self_attn.in_proj_bias")},
            "out_proj": dense(prefix + "self_attn.out_proj."),
            "norm_node": norm(prefix + "norm_node."), "norm1_node": norm(prefix + "norm1_node."),
            "linear1": dense(prefix + "linear1."), "linear2": dense(prefix + "linear2.")}

    width, d, de = config.selector_dim, config.node_dim, config.edge_dim
    if num_edge_heads:
        hd = width // num_edge_heads
        selector = {
            "in_proj_kernel": w(SELECTOR + "self_attn.in_proj_weight").T,
            "in_proj_bias": w(SELECTOR + "self_attn.in_proj_bias"),
            "mlp_hidden_kernel": jnp.zeros((width, width)).at[:hd, :hd].set(
                w(SELECTOR + "linear1.weight").T),
            "mlp_hidden_bias": jnp.zeros((width,)).at[:hd].set(w(SELECTOR + "linear1.bias")),
            "mlp_out_kernel": jnp.zeros((width,)).at[:hd].set(w(SELECTOR + "linear2.weight")[0]),
            "mlp_out_bias": w(SELECTOR + "linear2.bias")[0],
            "norm_node": norm(SELECTOR + "norm_node."), "norm_edge": norm(SELECTOR + "norm_edge.")}
    else:
        zeros = lambda *shape: jnp.zeros(shape)
        selector = {"in_proj_kernel": zeros(width, 3 * width), "in_proj_bias": zeros(3 * width),
                    "mlp_hidden_kernel": zeros(width, width), "mlp_hidden_bias": zeros(width),
                    "mlp_out_kernel": zeros(width), "mlp_out_bias": zeros(),
                    "norm_node": {"scale": jnp.ones(d), "bias": zeros(d)},
                    "norm_edge": {"scale": jnp.ones(de), "bias": zeros(de)}}
    params["edge_selector"] = selector
    return params


def batch_from_reference_inputs(inputs: Mapping[str, np.ndarray]) -> SceneBatch:
    """One-scene SceneBatch from the release's `obs_traj`/`pred_traj` (1, N, 2, T), -999 = missing."""
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


def params_to_torch(params, *, num_edge_heads: int, config: ModelConfig | None = None) -> dict:
    """Inverse of `params_from_torch`: gst_jax parameters (or gradients) -> torch names/layout.

    The selector's unused attention out_proj is not produced; with n = 0 no selector at all.
    """
    config = config or ModelConfig()
    out = {}

    def dense(prefix, p):
        out[prefix + "weight"], out[prefix + "bias"] = p["kernel"].T, p["bias"]

    def norm(prefix, p):
        out[prefix + "weight"], out[prefix + "bias"] = p["scale"], p["bias"]

    dense("node_embedding.", params["node_embedding"])
    dense("edge_embedding.", params["edge_embedding"])
    if num_edge_heads:
        selector = params["edge_selector"]
        hd = config.selector_dim // num_edge_heads
        out[SELECTOR + "self_attn.in_proj_weight"] = selector["in_proj_kernel"].T
        out[SELECTOR + "self_attn.in_proj_bias"] = selector["in_proj_bias"]
        norm(SELECTOR + "norm_node.", selector["norm_node"])
        norm(SELECTOR + "norm_edge.", selector["norm_edge"])
        out[SELECTOR + "linear1.weight"] = selector["mlp_hidden_kernel"][:hd, :hd].T
        out[SELECTOR + "linear1.bias"] = selector["mlp_hidden_bias"][:hd]
        out[SELECTOR + "linear2.weight"] = selector["mlp_out_kernel"][None, :hd]
        out[SELECTOR + "linear2.bias"] = selector["mlp_out_bias"][None]
    for layer in range(config.encoder_layers):
        prefix, p = ENCODER.format(layer), params[f"node_encoder_layers_{layer}"]
        out[prefix + "self_attn.in_proj_weight"] = p["in_proj"]["kernel"].T
        out[prefix + "self_attn.in_proj_bias"] = p["in_proj"]["bias"]
        dense(prefix + "self_attn.out_proj.", p["out_proj"])
        norm(prefix + "norm_node.", p["norm_node"])
        norm(prefix + "norm1_node.", p["norm1_node"])
        dense(prefix + "linear1.", p["linear1"])
        dense(prefix + "linear2.", p["linear2"])
    lstm = params["lstm"]
    out["lstm.weight_ih_l0"], out["lstm.weight_hh_l0"] = lstm["weight_ih"].T, lstm["weight_hh"].T
    out["lstm.bias_ih_l0"], out["lstm.bias_hh_l0"] = lstm["bias_ih"], lstm["bias_hh"]
    dense("hidden2pos.", params["hidden2pos"])
    return {name: np.asarray(value) for name, value in out.items()}


@functools.partial(jax.jit, static_argnames=("config", "hard", "return_attention"))
def _replay(params, batch, noise, controls, *, config, hard, return_attention):
    """Loss and outputs of one replayed run. n and ghost are traced: one compile per shape."""
    out = rollout_with_noise(params, noise, batch, config, controls, hard=hard,
                             return_attention=return_attention)
    return losses.batch_loss(config, out, batch), out


def _replay_inputs(state_dict, inputs, gumbel, normals, *, num_edge_heads, ghost, tau, output,
                   max_edge_heads):
    config = ModelConfig(max_edge_heads=max_edge_heads, output=output)
    params = params_from_torch(load_state_dict(state_dict), num_edge_heads=num_edge_heads,
                               ghost=ghost, config=config)
    batch = batch_from_reference_inputs(inputs)
    noise = noise_from_reference(gumbel, normals, batch.shape[2], config)
    return config, params, batch, noise, Controls.make(tau, num_edge_heads, ghost)


def reference_forward(state_dict, inputs: Mapping[str, np.ndarray], gumbel: Sequence[np.ndarray],
                      *, num_edge_heads: int, ghost: bool, tau: float, hard: bool,
                      normals: Sequence[np.ndarray] | None = None,
                      output: str = "deterministic", max_edge_heads: int = 16) -> dict:
    """Replay one release forward pass; outputs in the release's layouts (see the fixture)."""
    config, params, batch, noise, controls = _replay_inputs(
        state_dict, inputs, gumbel, normals, num_edge_heads=num_edge_heads, ghost=ghost,
        tau=tau, output=output, max_edge_heads=max_edge_heads)
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
