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
     "licence": null, ...,            # the licence and attribution where others made them
     "config_sha256": "..."}          # of this file's other fields (`config_digest`)

`load` checks every field of config.json against its range (`MODEL_FIELDS`, `DATA_FIELDS`,
`TRAIN_FIELDS`, read from each field's rule in `gst_jax.config`, the rule the flags and the
configs' construction read too: a time grid of 10^6 or 0 steps or a NaN step is refused, not
compiled), then
config.json's checksum: `config_sha256` is the SHA-256 of its other fields as canonical JSON
(sorted keys, no spaces, ASCII; `config_digest`), so an edit that keeps the parameters' layout
(`pred_len`, `obs_len`, `step_s`, `dropout`, the provenance) is detected like a damaged file.
Folders exported before config.json had a checksum have no `config_sha256`: they still load,
range-checked, with a warning saying how to re-export them (their fields are not damaged by
being old, and refusing them would strand every model users have handed out; the ranges are
what keep a wrong value out, the checksum what tells an edit). The shipped models all carry
one. Then the weights' checksum, that the file holds exactly the paths, shapes and dtype of
`init_params(model)` (what a training of that ModelConfig holds:
`abstract_train_state(model).params`), and that every value is finite (a NaN or infinite
parameter would make every prediction NaN). Anything else is refused in one line naming the
file and the field or tensor (`RunError`): a missing or damaged file, one that is not a
regular file (a FIFO, a link to /dev/zero) or holds more than MAX_WEIGHTS_BYTES /
MAX_CONFIG_BYTES (refused unread), a file of another model, a value out of range.
`pretrained:NAME` names a model shipped in the package (`gst_jax/pretrained/NAME/`: these
two files and its record, meta.json). `python -m gst_jax.pretrained export MODEL --out DIR`
writes such a folder from any model, `load_model(DIR)` and `crowdnav.load(DIR)` read it.

One job, though over 400 lines: the format, written and read; most of it is the checks a read
makes (of the fields, by their rules in `gst_jax.config`; of the checksums, tensors and
values), kept beside the writer so that what is written is what is checked.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import jax
import numpy as np
import safetensors.numpy

from gst_jax.config import DataConfig, ModelConfig, TrainConfig, rules
from gst_jax.errors import RunError
from gst_jax.model.gst import init_params
from gst_jax.model.heads import HEADS
from gst_jax.regular_files import read_regular

__all__ = ["Weights", "config_digest", "expected_layout", "flatten", "folder_of", "is_weights",
           "layout_problems", "load", "read_config", "save", "shipped", "shipped_folder"]

FORMAT = "gst_jax.weights/1"
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
# The models shipped in the package: `pretrained:NAME` is the folder SHIPPED / NAME.
SHIPPED = Path(__file__).parents[1] / "pretrained"
PRETRAINED = "pretrained:"
# A shipped model's record: its configs, how it was made, its test metrics and fixed-key check.
SHIPPED_RECORD = "meta.json"
# config.json's own checksum: of its other fields, as canonical JSON (`config_digest`).
CONFIG_DIGEST = "config_sha256"
# The most either file may hold, read only where it is a regular file (`gst_jax.regular_files`:
# a FIFO would block the read, a link to /dev/zero never end it). The shipped models' are 1.3 MB
# and 3.4 kB.
MAX_WEIGHTS_BYTES = 2**30
MAX_CONFIG_BYTES = 2**20

# A field's range: `check(value)` is None where the value is in it, else what it must be.
Check = Callable[[Any], "str | None"]


def integers(low: int, high: int) -> Check:
    """Integers (not booleans) from low to high."""
    def check(value):
        if type(value) is not int or not low <= value <= high:
            return f"must be an integer from {low} to {high}"
    return check


def one_of(choices: Callable[[], Any]) -> Check:
    """One of `choices()` (read when checked: HEADS may grow)."""
    def check(value):
        known = tuple(choices())
        if not isinstance(value, str) or value not in known:
            return f"must be one of {', '.join(known)}"
    return check


def boolean(value) -> str | None:
    return None if type(value) is bool else "must be true or false"


def text(value) -> str | None:
    return None if value is None or isinstance(value, str) else "must be a string or null"


def shown(value) -> str:
    """A value as a message shows it: short, and an integer of 10^5000 without converting it
    (Python refuses to write integers of more than 4300 digits)."""
    if type(value) is int and value.bit_length() > 64:
        return f"{'-' if value < 0 else ''}an integer of {value.bit_length()} bits"
    written = repr(value)
    return written if len(written) <= 40 else written[:37] + "..."


def field_problem(values: Any, fields: Mapping[str, Check], where: str = "",
                  retired: frozenset = frozenset(), known_only: bool = True) -> str | None:
    """What is wrong with the first field of `values` out of its range, in words naming the
    field (`where.name`, or `name` where `where` is empty) and its value; None where every
    field is in range. Fields that `values` lacks are not checked (they take their defaults);
    names not in `fields` are refused where known_only (but `retired` ones, which from_dict
    drops, pass)."""
    prefix = f"{where}." if where else ""
    if not isinstance(values, Mapping):
        return f"{where or 'it'} is {shown(values)}, not an object of fields"
    for name, value in values.items():
        if name in fields:
            if (problem := fields[name](value)) is not None:
                return f"{prefix}{name} is {shown(value)}: {problem}"
        elif known_only and name not in retired:
            return f"{where or 'it'} has a field {shown(name)} that it does not know"
    return None


def schema_checks(config_class) -> dict[str, Check]:
    """The checks of a config's fields in config.json: each field's rule (`gst_jax.config`:
    its type, range or choices), in a file's words ("must be an integer from 1 to 1000")."""
    return {name: rule.problem for name, rule in rules(config_class).items()}


def required_text(value) -> str | None:
    return None if isinstance(value, str) else "must be a string"


# The ranges of config.json's fields: every field's rule in gst_jax.config (their bounds and
# why they are where they are are written there), with two read elsewhere. A model's output
# is one of the heads of the model layer (HEADS, which may grow). A scene's name rule is
# checked where the run is built from the file (`DataConfig`, refused in its own words and
# naming the file: `runs.load_weights_run`); here it must be a string.
MODEL_FIELDS: dict[str, Check] = {**schema_checks(ModelConfig),
                                  "output": one_of(lambda: HEADS)}
DATA_FIELDS: dict[str, Check] = {**schema_checks(DataConfig), "scene": required_text}
TRAIN_FIELDS: dict[str, Check] = schema_checks(TrainConfig)


def sha256_text(value) -> str | None:
    if isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value):
        return None
    return "must be a SHA-256: 64 lowercase hex digits"


RECORD_FIELDS: dict[str, Check] = {"sha256": sha256_text, CONFIG_DIGEST: sha256_text,
                                   "epoch": integers(0, 10**6), "source": text, "licence": text}


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
        return json.loads(_read_config_bytes(folder / CONFIG_FILE)).get("format") == FORMAT
    except (OSError, ValueError, AttributeError, RecursionError, RunError):
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


def config_digest(config: Mapping) -> str:
    """SHA-256 of a config.json's fields other than `config_sha256`, as canonical JSON: sorted
    keys, no spaces, ASCII (so that indenting or reordering the file keeps it). A value JSON
    cannot hold (NaN) has no digest: ValueError."""
    fields = {k: v for k, v in config.items() if k != CONFIG_DIGEST}
    canonical = json.dumps(fields, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                           allow_nan=False)
    return hashlib.sha256(canonical.encode("ascii")).hexdigest()


def save(folder: str | Path, model_config: ModelConfig, params, record: Mapping | None = None
         ) -> Path:
    """Write `folder/model.safetensors` and `folder/config.json` (the format, the checksum,
    the ModelConfig, `record`: data, train, epoch, source, licence, ..., and config.json's own
    checksum); returns folder. Refuses parameters that are not those of `model_config`, or not
    finite, and a config.json that `load` would refuse."""
    folder = Path(folder)
    tensors = flatten(params)
    what = f"{folder / WEIGHTS_FILE} (not written)"
    _check_layout(tensors, model_config, what)
    _check_finite(tensors, what)
    raw = safetensors.numpy.save(tensors)
    config = {"format": FORMAT, "sha256": hashlib.sha256(raw).hexdigest(),
              "model": dataclasses.asdict(model_config), **(record or {})}
    _check_fields(config, f"{folder / CONFIG_FILE} (not written)")
    try:
        config[CONFIG_DIGEST] = config_digest(config)
        text = json.dumps(config, indent=2) + "\n"
    except (TypeError, ValueError) as error:     # a record of others: a set, a NaN, ...
        raise RunError(f"{folder / CONFIG_FILE} (not written): its record holds a value that "
                       f"JSON cannot ({error})") from None
    folder.mkdir(parents=True, exist_ok=True)
    (folder / WEIGHTS_FILE).write_bytes(raw)
    (folder / CONFIG_FILE).write_text(text)
    return folder


def read_config(spec: str | Path) -> dict:
    """The config.json of a weights folder (not checked against its weights)."""
    path = folder_of(spec) / CONFIG_FILE
    try:
        config = json.loads(_read_config_bytes(path))
    except FileNotFoundError:
        raise RunError(f"{path}: no such file (a weights folder holds {WEIGHTS_FILE} and "
                       f"{CONFIG_FILE})") from None
    except (OSError, ValueError) as error:
        raise RunError(f"{path}: not readable ({error})") from None
    except RecursionError:
        raise RunError(f"{path}: not readable (JSON nested too deeply)") from None
    if not isinstance(config, dict) or config.get("format") != FORMAT:
        raise RunError(f"{path}: not a gst_jax weights config (no \"format\": \"{FORMAT}\")")
    for key in ("sha256", "model"):
        if key not in config:
            raise RunError(f"{path}: has no {key!r}")
    return config


def _read_config_bytes(path: Path) -> bytes:
    return read_regular(path, MAX_CONFIG_BYTES, "gst_jax.model.weights.MAX_CONFIG_BYTES",
                        RunError)


def load(spec: str | Path) -> Weights:
    """Read a weights folder (`pretrained:NAME`, a folder, its model.safetensors or config.json),
    checked: config.json's fields and checksum, the weights' checksum, then the paths, shapes
    and dtype its ModelConfig expects and that every value is finite."""
    folder = folder_of(spec)
    config = read_config(folder)
    config_path = folder / CONFIG_FILE
    _check_fields(config, str(config_path))
    _check_config_digest(config, config_path)
    path = folder / WEIGHTS_FILE
    try:
        model_config = ModelConfig.from_dict(config["model"])
    except (TypeError, ValueError) as error:
        raise RunError(f"{config_path}: not a model config ({error})") from None
    try:
        raw = read_regular(path, MAX_WEIGHTS_BYTES, "gst_jax.model.weights.MAX_WEIGHTS_BYTES",
                           RunError)
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
    _check_finite(tensors, str(path))
    like = _abstract_params(model_config)
    names = list(flatten_abstract(like))
    # One transfer for all of them: an asarray per tensor dispatches ~200 small programs.
    params = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(like),
                                          jax.device_put([tensors[name] for name in names]))
    return Weights(folder, model_config, params, config)


def _check_fields(config: Mapping, what: str):
    """Refuse, in one line naming the field and its value, a config.json field out of its
    range (the model's, the data's and training's, the record's)."""
    problem = (field_problem(config["model"], MODEL_FIELDS, "model")
               or field_problem(config.get("data", {}), DATA_FIELDS, "data",
                                DataConfig.RETIRED)
               or field_problem(config.get("train", {}), TRAIN_FIELDS, "train",
                                TrainConfig.RETIRED)
               or field_problem({k: v for k, v in config.items() if k in RECORD_FIELDS},
                                RECORD_FIELDS))
    commands = config.get("commands", [])
    if problem is None and not (isinstance(commands, list)
                                and all(isinstance(c, str) for c in commands)):
        problem = f"commands is {shown(commands)}: must be a list of strings"
    if problem is not None:
        raise RunError(f"{what}: {problem}")


def _check_config_digest(config: Mapping, path: Path):
    """config.json's checksum: refused where it does not match; warned where it has none
    (exported before config.json had one)."""
    recorded = config.get(CONFIG_DIGEST)
    if recorded is None:
        warnings.warn(f"{path} has no {CONFIG_DIGEST} (exported before config.json had a "
                      "checksum): its fields are in range, but an edit within their ranges "
                      "cannot be detected; `python -m gst_jax.pretrained export "
                      f"{path.parent} --out NEW_FOLDER` writes a copy that has one",
                      stacklevel=3)
        return
    try:
        digest = config_digest(config)
    except ValueError:      # NaN or infinity where no range is checked (crowdnav_args, ...)
        raise RunError(f"{path}: holds a NaN or infinite value, which its {CONFIG_DIGEST} "
                       "cannot cover: the file was edited after export") from None
    if digest != recorded:
        raise RunError(f"{path}: its fields' SHA-256 {digest[:16]}... is not the "
                       f"{recorded[:16]}... its {CONFIG_DIGEST} records: the file was edited or "
                       "damaged after export")


def _check_finite(tensors: Mapping[str, np.ndarray], what: str):
    """Refuse, in one line naming the tensor, parameters that are NaN or infinite: one would
    make every prediction NaN."""
    for name, tensor in tensors.items():
        finite = np.isfinite(tensor)
        if not finite.all():
            where = tuple(int(i) for i in np.argwhere(~finite)[0])
            raise RunError(f"{what}: tensor {name} holds {int((~finite).sum())} non-finite "
                           f"value(s) of {finite.size} (the first, {tensor[where]}, at index "
                           f"{list(where)}): parameters must be finite")


def layout_problems(tensors: Mapping[str, np.ndarray],
                    expected: Mapping[str, tuple[tuple[int, ...], Any]]) -> list[str]:
    """What keeps `tensors` from being exactly `expected` (name -> (shape, dtype)): tensors
    missing, unexpected, or of another shape or dtype, one phrase each (none: they are)."""
    problems = [f"no {name}" for name in expected if name not in tensors]
    problems += [f"unexpected {name}" for name in tensors if name not in expected]
    problems += [f"{name} is {tensors[name].dtype}{list(tensors[name].shape)}, expected "
                 f"{dtype}{list(shape)}" for name, (shape, dtype) in expected.items()
                 if name in tensors and (tensors[name].shape, tensors[name].dtype)
                 != (shape, dtype)]
    return problems


def _check_layout(tensors: Mapping[str, np.ndarray], model_config: ModelConfig, what: str):
    """Refuse, in one line, tensors that are not exactly the parameters of model_config."""
    problems = layout_problems(tensors, expected_layout(model_config))
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise RunError(f"{what}: not the parameters of its model config: "
                       f"{'; '.join(problems[:3])}{more}")
