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

Files in and out:
- trajectories: `data.readers` reads text (`frame ped x y`, a tracker's CSV) and TrajNet++
  ndjson into `data.Tracks`, and puts them on the model's steps (`data.readers.to_model_rate`);
  `data.windows` cuts them into scene windows and `data.protocols` splits those;
- predictions: `prediction_files` writes them as TrajNet++ ndjson and reads them back; a
  TrajNet++ file's own scenes (`data.trajnet`) are scored as its benchmark does
  (`trajnet_metrics`);
- models: `model.weights` (`model.safetensors` and `config.json`, the shipped models'
  format), `interop` (the authors' PyTorch weights), `io.workdir` and `io.checkpoints` (a
  training run's folder and its checkpoints).

The model's layers (`model`): `model.selector` (the edge Gumbel selector), `model.encoder`
(the node Transformer encoder), `model.recurrent` (the masked LSTM), `model.temporal` (the
release's TCN readout) and `model.heads` (the output heads), on `model.layers` (initialisers
and small shared layers), put together in `model.gst`; `model.controls` holds the traced
switches of a forward pass.
"""

import importlib
import sys

# Each public name and the module that defines it; a module is imported when its name is
# first used, so that `import gst_jax.data` (numpy only) or a command that prints statistics
# does not pay for importing jax, flax and orbax.
_PUBLIC = {
    "Controls": "gst_jax.model", "DataConfig": "gst_jax.config", "ModelConfig": "gst_jax.config",
    "Prediction": "gst_jax.predict", "SceneBatch": "gst_jax.data", "TrainConfig": "gst_jax.config",
    "init_params": "gst_jax.model", "load_pretrained": "gst_jax.pretrained",
    "make_batch": "gst_jax.data", "make_predict": "gst_jax.predict",
}
# The public names, and the modules of the API reference (`pdoc gst_jax`).
__all__ = sorted(_PUBLIC) + ["config", "conformal", "coverage", "crowdnav", "data", "errors",
                             "evaluation", "graph", "gumbel", "interop", "io", "losses",
                             "metrics", "model", "predict", "prediction_files", "pretrained",
                             "rollout", "runs", "simulate", "stream", "training",
                             "trajnet_metrics"]


def _bind_for_pdoc() -> None:
    """What pdoc needs to build the API reference without a warning (README, "More"): it reads
    the names of `__all__` from the module's `__dict__`, never through `__getattr__`, so they
    are bound here; and it resolves the annotations of a NamedTuple's constructor in the module
    of its `__new__`, which `namedtuple` leaves unnamed (mitmproxy/pdoc#765), so each of ours
    is named. Only where pdoc is imported: it imports jax and every public module."""
    for name in __all__:
        if name in _PUBLIC:
            globals()[name] = __getattr__(name)
        else:
            importlib.import_module(f"{__name__}.{name}")
    modules = [m for n, m in list(sys.modules.items()) if n.startswith(f"{__name__}.") and m]
    for value in [value for module in modules for value in vars(module).values()]:
        if isinstance(value, type) and issubclass(value, tuple) and hasattr(value, "_fields"):
            if getattr(value.__new__, "__module__", "").startswith("namedtuple_"):
                value.__new__.__module__ = value.__module__


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'gst_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))


if "pdoc" in sys.modules:
    _bind_for_pdoc()
