"""gst_jax: the Gumbel Social Transformer (Huang et al., RA-L 2022) in JAX/Flax."""

from gst_jax.config import DataConfig, ModelConfig

__all__ = ["DataConfig", "ModelConfig"]
