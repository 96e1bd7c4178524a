"""gst_jax: the Gumbel Social Transformer (Huang et al., RA-L 2022) in JAX/Flax.

    import gst_jax, jax
    config = gst_jax.ModelConfig()
    params = gst_jax.init_params(config, jax.random.key(0))
    predict = gst_jax.make_predict(config, num_samples=20)
    batch = gst_jax.make_batch(observed_xy)      # (B, 8, N, 2), NaN = not detected
    prediction = predict(params, jax.random.key(1), batch)
    prediction.positions                          # (20, B, 12, N, 2)

    config, params = gst_jax.load_pretrained("eth")  # shipped weights, see gst_jax/pretrained
"""

from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.data import SceneBatch, make_batch
from gst_jax.model import Controls, init_params
from gst_jax.predict import Prediction, make_predict
from gst_jax.pretrained import load_pretrained

__all__ = ["Controls", "DataConfig", "ModelConfig", "Prediction", "SceneBatch", "TrainConfig",
           "init_params", "load_pretrained", "make_batch", "make_predict"]
