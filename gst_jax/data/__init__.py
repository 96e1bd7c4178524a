"""numpy-only data layer: readers, windowing, protocols, batching. Never imports jax."""

from gst_jax.data.batch import SceneBatch

__all__ = ["SceneBatch"]
