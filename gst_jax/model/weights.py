"""A model's parameters as files anyone can read: `model.safetensors` plus `config.json`.

No pickle and no torch: the parameters are a safetensors file, one float32 tensor per leaf of
the Flax parameter tree, named by its path with its keys joined by '/': `node_embedding/kernel`,
`node_encoder_layers_0/in_proj/bias`, `lstm/weight_ih`, `edge_selector/mlp_out_bias` (a 0-d
tensor), ... (`flatten`); every kernel is Flax's (in, out). Any safetensors reader opens it
(`safetensors.numpy.load_file`); this module writes and reads its bytes with safetensors' numpy
API (`save`, `load`), so that the checksum is of the very bytes read. `config.json` beside it
says what they are:

    {"format": "gst_jax.weights/1",   # this layout
     "sha256": "...",                 # of model.safetensors, checked before it is read
     "model": {...},                  # the ModelConfig: the tree's paths and shapes follow
     "data": {...}, "train": {...},   # DataConfig and TrainConfig of the training (provenance)
     "epoch": 100, "source": "...",   # the epoch and where the parameters came from
     "licence": null, ...}            # the licence and attribution where others made them

`load` checks the checksum, then that the file holds exactly the paths, shapes and dtype of
`init_params(model)` (what a training of that ModelConfig holds:
`abstract_train_state(model).params`), and refuses anything else in one line naming the file
(`RunError`): a missing or damaged file, a file of another model. `pretrained:NAME` names a
model shipped in the package (`gst_jax/pretrained/NAME/`: these two files and its record,
meta.json). `python -m gst_jax.pretrained export MODEL --out DIR` writes such a folder from any
model, `load_model(DIR)` and `crowdnav.load(DIR)` read it.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import safetensors.numpy

from gst_jax.config import ModelConfig
from gst_jax.errors import RunError
from gst_jax.model.gst import init_params

FORMAT = "gst_jax.weights/1"
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
# The models shipped in the package: `pretrained:NAME` is the folder SHIPPED / NAME.
SHIPPED = Path(__file__).parents[1] / "pretrained"
PRETRAINED = "pretrained:"
# A shipped model's record: its configs, how it was made, its test metrics and fixed-key check.
SHIPPED_RECORD = "meta.json"


@dataclasses.dataclass(frozen=True)
class Weights:
    """A weights folder read back: its model, parameters (jax arrays) and config.json."""

    folder: Path
    model_config: ModelConfig
    params: Any
    config: dict


def shipped() -> list[str]:
    """Names of the shipped models, e.g. ['crowdnav_sj', 'eth_d', ...]."""
    return sorted(p.name for p in SHIPPED.iterdir() if (p / SHIPPED_RECORD).exists())


def shipped_folder(name: str) -> Path:
    """The folder of a shipped model; 'eth' means GST (D) on eth ('eth_d')."""
    names = shipped()
    for candidate in (name, f"{name}_d"):
        if candidate in names:
            return SHIPPED / candidate
    raise RunError(f"no pretrained model {name!r}; shipped: {', '.join(names) or 'none'}")


def is_weights(spec: str | Path) -> bool:
    """Whether a model name is `pretrained:NAME`, a weights folder (one holding model.safetensors,
    or a config.json of this format), its config.json or a path to a .safetensors file."""
    spec = str(spec)
    if spec.startswith(PRETRAINED) or spec.endswith(".safetensors"):
        return True
    folder = Path(spec).parent if Path(spec).name == CONFIG_FILE else Path(spec)
    if (folder / WEIGHTS_FILE).exists():
        return True
    try:
        return json.loads((folder / CONFIG_FILE).read_text()).get("format") == FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def folder_of(spec: str | Path) -> Path:
    """The weights folder a model name means: `pretrained:NAME`, a folder, or its
    model.safetensors or config.json."""
    spec = str(spec)
    if spec.startswith(PRETRAINED):
        return shipped_folder(spec.removeprefix(PRETRAINED))
    path = Path(spec)
    if path.suffix == ".safetensors" and path.name != WEIGHTS_FILE:
        raise RunError(f"{path}: a weights folder's parameters are its {WEIGHTS_FILE}, beside "
                       f"its {CONFIG_FILE}; name the folder")
    return path.parent if path.name in (WEIGHTS_FILE, CONFIG_FILE) else path


def _key_name(key) -> str:
    for attribute in ("key", "name", "idx"):
        if hasattr(key, attribute):
            return str(getattr(key, attribute))
    return str(key)


def flatten(params) -> dict[str, np.ndarray]:
    """The parameter tree as {'/'-joined path: numpy array}, e.g. 'lstm/weight_ih'."""
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    return {"/".join(_key_name(k) for k in path): np.asarray(leaf, order="C")
            for path, leaf in leaves}


@functools.lru_cache(maxsize=16)
def _abstract_params(model_config: ModelConfig):
    return jax.eval_shape(lambda key: init_params(model_config, key), jax.random.key(0))


def expected_layout(model_config: ModelConfig) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """{path: (shape, dtype)} of the parameters of a ModelConfig (as a training holds them)."""
    return {name: (tuple(leaf.shape), np.dtype(leaf.dtype))
            for name, leaf in flatten_abstract(_abstract_params(model_config)).items()}


def flatten_abstract(tree) -> dict[str, Any]:
    """Like `flatten`, for a tree of shapes (`jax.ShapeDtypeStruct`s)."""
    return {"/".join(_key_name(k) for k in path): leaf
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def save(folder: str | Path, model_config: ModelConfig, params, record: Mapping | None = None
         ) -> Path:
    """Write `folder/model.safetensors` and `folder/config.json` (the format, the checksum,
    the ModelConfig and `record`: data, train, epoch, source, licence, ...); returns folder.
    Refuses parameters that are not those of `model_config`."""
    folder = Path(folder)
    tensors = flatten(params)
    _check_layout(tensors, model_config, f"{folder / WEIGHTS_FILE} (not written)")
    raw = safetensors.numpy.save(tensors)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / WEIGHTS_FILE).write_bytes(raw)
    config = {"format": FORMAT, "sha256": hashlib.sha256(raw).hexdigest(),
              "model": dataclasses.asdict(model_config), **(record or {})}
    (folder / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")
    return folder


def read_config(spec: str | Path) -> dict:
    """The config.json of a weights folder (not checked against its weights)."""
    path = folder_of(spec) / CONFIG_FILE
    try:
        config = json.loads(path.read_text())
    except FileNotFoundError:
        raise RunError(f"{path}: no such file (a weights folder holds {WEIGHTS_FILE} and "
                       f"{CONFIG_FILE})") from None
    except (OSError, ValueError) as error:
        raise RunError(f"{path}: not readable ({error})") from None
    if not isinstance(config, dict) or config.get("format") != FORMAT:
        raise RunError(f"{path}: not a gst_jax weights config (no \"format\": \"{FORMAT}\")")
    for key in ("sha256", "model"):
        if key not in config:
            raise RunError(f"{path}: has no {key!r}")
    return config


def load(spec: str | Path) -> Weights:
    """Read a weights folder (`pretrained:NAME`, a folder, its model.safetensors or config.json),
    checked: checksum, then the paths, shapes and dtype its ModelConfig expects."""
    folder = folder_of(spec)
    config = read_config(folder)
    path = folder / WEIGHTS_FILE
    try:
        model_config = ModelConfig.from_dict(config["model"])
    except (TypeError, ValueError) as error:
        raise RunError(f"{folder / CONFIG_FILE}: not a model config ({error})") from None
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise RunError(f"{path}: no such file") from None
    except OSError as error:
        raise RunError(f"{path}: not readable ({error})") from None
    digest = hashlib.sha256(raw).hexdigest()
    if digest != config["sha256"]:
        raise RunError(f"{path}: SHA-256 {digest[:16]}... is not the {str(config['sha256'])[:16]}"
                       f"... its {CONFIG_FILE} records: the file is damaged or not the one "
                       "its config describes")
    try:
        tensors = safetensors.numpy.load(raw)
    except Exception as error:  # safetensors raises its own error type on a malformed file
        raise RunError(f"{path}: not a safetensors file ({error})") from None
    _check_layout(tensors, model_config, str(path))
    like = _abstract_params(model_config)
    names = list(flatten_abstract(like))
    params = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(like),
                                          [jnp.asarray(tensors[name]) for name in names])
    return Weights(folder, model_config, params, config)


def _check_layout(tensors: Mapping[str, np.ndarray], model_config: ModelConfig, what: str):
    """Refuse, in one line, tensors that are not exactly the parameters of model_config."""
    expected = expected_layout(model_config)
    problems = [f"no {name}" for name in expected if name not in tensors]
    problems += [f"unexpected {name}" for name in tensors if name not in expected]
    problems += [f"{name} is {tensors[name].dtype}{list(tensors[name].shape)}, expected "
                 f"{dtype}{list(shape)}" for name, (shape, dtype) in expected.items()
                 if name in tensors and (tensors[name].shape, tensors[name].dtype)
                 != (shape, dtype)]
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise RunError(f"{what}: not the parameters of its model config: "
                       f"{'; '.join(problems[:3])}{more}")
