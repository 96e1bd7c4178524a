"""The conformal methods, one module each; `gst_jax.conformal` re-exports them."""
