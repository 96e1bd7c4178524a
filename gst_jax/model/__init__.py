"""Flax Linen layers of the Gumbel Social Transformer."""

from gst_jax.model.controls import Controls
from gst_jax.model.gst import GST, Params, init_params

__all__ = ["Controls", "GST", "Params", "init_params"]
