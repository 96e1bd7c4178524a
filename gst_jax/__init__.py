"""gst_jax: the Gumbel Social Transformer (Huang et al., RA-L 2022) in JAX/Flax.

    import gst_jax, jax
    config = gst_jax.ModelConfig()
    params = gst_jax.init_params(config, jax.random.key(0))
    predict = gst_jax.make_predict(config, num_samples=20)
    batch = gst_jax.make_batch(observed_xy)      # (B, 8, N, 2), NaN = not detected
    prediction = predict(params, jax.random.key(1), batch)
    prediction.positions                          # (20, B, 12, N, 2)

    config, params = gst_jax.load_pretrained("eth")  # shipped weights, see gst_jax/pretrained

The layers, bottom up: `data` (numpy), `graph` and `gumbel`, `model`, `rollout`, then
`predict`, `losses`, `metrics`, `interop`, `simulate`; `training`, `evaluation` and `runs`
(work directories) above them; the commands (`python -m gst_jax.train`, ...) on top.
"""

from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.data import SceneBatch, make_batch
from gst_jax.model import Controls, init_params
from gst_jax.predict import Prediction, make_predict

__all__ = ["Controls", "DataConfig", "ModelConfig", "Prediction", "SceneBatch", "TrainConfig",
           "init_params", "load_pretrained", "make_batch", "make_predict"]


def __getattr__(name: str):
    # Checkpoints need orbax, a heavy import: loaded when a shipped model is first asked for.
    if name == "load_pretrained":
        from gst_jax.pretrained import load_pretrained
        return load_pretrained
    raise AttributeError(f"module 'gst_jax' has no attribute {name!r}")
