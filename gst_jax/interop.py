"""Interoperability with the authors' PyTorch release: its weights as gst_jax parameters and
back.

- `params_from_torch`: a release state dict (torch names -> arrays, or a `.pt` file) ->
  gst_jax parameters in the traced-n layout.
- `params_to_torch`: gst_jax parameters (or gradients) -> the release's names and layouts.
- `check_state_dict`: refuses, in one line naming the file and the tensor, a state dict that
  lacks a tensor of a model, holds one of another shape, or one that is not finite float32
  (`params_from_torch` would fail with a bare KeyError, or build parameters that fail later).

torch is not needed: `.pt` files are read by `gst_jax.safe_pickle`, which admits tensors,
plain values and numpy scalars and refuses anything else a file would run.
Replaying a release run for the parity tests is `gst_jax.testing.release`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import jax.numpy as jnp
import numpy as np

from gst_jax.config import ModelConfig
from gst_jax.errors import DataError
from gst_jax.model import Params, weights
from gst_jax.safe_pickle import MAX_BYTES, read_torch

SELECTOR = "gumbel_social_transformer.edge_selector."
ENCODER = "gumbel_social_transformer.node_encoder_layers.{}."
# gst_updated (CrowdNav++) keeps its node embedding inside its transformer.
GST_UPDATED_NODE_EMBEDDING = "gumbel_social_transformer.node_embedding."


def load_state_dict(source: str | Path | Mapping[str, Any], max_bytes: int = MAX_BYTES,
                    reason: str = "gst_jax.safe_pickle.MAX_BYTES",
                    declared_copies: int | None = None) -> dict[str, np.ndarray]:
    """A mapping of torch names to arrays, from a mapping or a `.pt` file (the release's
    checkpoint layout, `{"model_state_dict": ..., ...}`, or a bare state dict); reading the
    file may allocate at most `max_bytes`, and at most `declared_copies` times the bytes its
    zip entries declare (`gst_jax.safe_pickle.read_torch`)."""
    if isinstance(source, Mapping):
        return {name: np.asarray(value) for name, value in source.items()}
    loaded = read_torch(source, max_bytes, reason, declared_copies)
    if isinstance(loaded, Mapping) and "model_state_dict" in loaded:
        loaded = loaded["model_state_dict"]
    if not (isinstance(loaded, Mapping) and loaded
            and all(isinstance(value, np.ndarray) for value in loaded.values())):
        raise DataError(f"{source}: holds no state dict (a mapping of names to tensors)")
    return dict(loaded)


def expected_state_dict(config: ModelConfig) -> dict[str, tuple[int, ...]]:
    """{torch name: shape} of the tensors `params_from_torch` reads for a model of `config` (n
    = config.num_edge_heads), in the release's names; `check_state_dict` also takes
    gst_updated's node embedding name and, with n = 0, no edge embedding."""
    # Zero-stride views of one zero each: the shapes of any model its config allows (a
    # hostile args.pickle's 64 layers 4096 wide) without allocating them.
    zeros = {name: np.broadcast_to(np.zeros((), dtype), shape)
             for name, (shape, dtype) in weights.expected_layout(config).items()}
    tree: dict = {}
    for name, value in zeros.items():
        *path, leaf = name.split("/")
        node = tree
        for key in path:
            node = node.setdefault(key, {})
        node[leaf] = value
    torch = params_to_torch(tree, num_edge_heads=config.num_edge_heads, config=config)
    return {name: value.shape for name, value in torch.items()}


def check_state_dict(state_dict: Mapping[str, Any], config: ModelConfig, where: str):
    """Refuse, in one line naming `where` and the tensor, a state dict that is not one of a
    model of `config`: a tensor missing, of another shape, not floating point or not finite.
    Tensors the model does not read (an optimizer's, metrics) are let be."""
    expected = expected_state_dict(config)
    if GST_UPDATED_NODE_EMBEDDING + "weight" in state_dict:
        expected = {name.replace("node_embedding.", GST_UPDATED_NODE_EMBEDDING, 1)
                    if name.startswith("node_embedding.") else name: shape
                    for name, shape in expected.items()}
    if not config.num_edge_heads and "edge_embedding.weight" not in state_dict:
        expected = {k: v for k, v in expected.items() if not k.startswith("edge_embedding.")}
    missing = [name for name in expected if name not in state_dict]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise DataError(f"{where}: has no tensor {missing[0]}{more}, which its model reads")
    for name, shape in expected.items():
        value = state_dict[name]
        if not isinstance(value, np.ndarray) or value.dtype not in (np.float32, np.float64):
            raise DataError(f"{where}: {name} is "
                            f"{getattr(value, 'dtype', type(value).__name__)}, not a float32 "
                            "(or float64) tensor")
        if value.shape != shape:
            raise DataError(f"{where}: {name} is of shape {list(value.shape)}, where its "
                            f"model's is {list(shape)}")
        finite = np.isfinite(value)
        if not finite.all():
            raise DataError(f"{where}: {name} holds {int((~finite).sum())} non-finite "
                            f"value(s) of {finite.size}: parameters must be finite")


def params_from_torch(state_dict, *, num_edge_heads: int, ghost: bool,
                      max_edge_heads: int = 16, config: ModelConfig | None = None) -> Params:
    """Convert release weights into gst_jax parameters (traceable, so grads flow back).

    PyTorch Linear stores W as (out, in); flax kernels are (in, out). The selector's per-head
    MLP (head_dim = 128 / n) goes into the top-left block of the padded 128 x 128 weight.
    With n = 0 the release has no selector; its parameters are zero (and unused). The later
    gst_updated (CrowdNav++) keeps the node embedding inside its transformer and, without a
    selector, has no edge embedding (zero here, and unused).
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

    node_embedding = ("node_embedding." if "node_embedding.weight" in state_dict
                      else GST_UPDATED_NODE_EMBEDDING)
    edge_embedding = (dense("edge_embedding.") if "edge_embedding.weight" in state_dict
                      else {"kernel": jnp.zeros((2, config.edge_dim)),
                            "bias": jnp.zeros(config.edge_dim)})
    params: dict[str, Any] = {
        "node_embedding": dense(node_embedding), "edge_embedding": edge_embedding,
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
        selector: dict[str, Any] = {
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


def params_to_torch(params: Params, *, num_edge_heads: int, config: ModelConfig | None = None
                    ) -> dict:
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
