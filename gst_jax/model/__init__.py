"""Flax Linen layers of the Gumbel Social Transformer."""

from gst_jax.model.controls import Controls
from gst_jax.model.gst import GST, Params, init_params

__all__ = ["Controls", "GST", "Params", "init_params",
           # The layers and the weights format, pages of their own in the API reference.
           "selector", "encoder", "recurrent", "temporal", "heads", "layers", "gst", "controls",
           "weights"]
